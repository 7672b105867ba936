"""The documentation holds: the README's Python example runs as written, and quietly (no EGL
clean-up noise at exit); the README stays a newcomer's first page that links every page of
docs/; every relative link of the README and docs/ reaches a file (and heading) of the repo; and
every `ccdata` / `ccfit` command of their shell blocks parses with the real command lines."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [README, *DOCS]
FENCE = re.compile(r"^```.*?^```", flags=re.S | re.M)
LINK = re.compile(r"\]\(([^)\s]+)\)")


def test_the_readme_api_example_runs():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    (example,) = [b for b in blocks if "ccdata.make_env" in b]
    # its last line's value, as the comment beside it states
    shown = re.search(r"# ([\d.]+); 0 = floor", example).group(1)
    last = example.strip().splitlines()[-1].split("#")[0]
    script = example + f"\nprint(round({last}, 1))\n"
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == shown
    assert "Exception ignored" not in proc.stderr and "Traceback" not in proc.stderr


def test_the_readme_is_a_first_page_that_links_every_docs_page():
    text = README.read_text()
    assert len(text.splitlines()) <= 200, "the README is a first page; reference goes to docs/"
    assert text.startswith("# ") and "make demo" in text.split("\n## ")[0]
    linked = {target.split("#")[0] for target in LINK.findall(FENCE.sub("", text))}
    assert DOCS and {f"docs/{page.name}" for page in DOCS} <= linked
    assert "results/README.md" in linked
    for page in DOCS:  # each page opens with its title, then what it is for
        title, blank, purpose = page.read_text().splitlines()[:3]
        assert title.startswith("# ") and not blank and purpose[:1].isalpha(), page.name


def _slug(heading: str) -> str:
    """GitHub's anchor for a Markdown heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    found: set[str] = set()
    for heading in re.findall(r"^#+ (.+)$", FENCE.sub("", page.read_text()), flags=re.M):
        slug, n = _slug(heading), 1
        while slug in found:  # a repeated heading gets -1, -2, ...
            slug, n = f"{_slug(heading)}-{n}", n + 1
        found.add(slug)
    return found


def test_every_relative_link_reaches_a_file_and_heading():
    broken = []
    for page in PAGES:
        for target in LINK.findall(FENCE.sub("", page.read_text())):
            if re.match(r"[a-z]+:", target):  # https:, mailto:
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            where = f"{page.relative_to(ROOT)}: {target}"
            if not dest.is_relative_to(ROOT) or not dest.exists():
                broken.append(f"{where} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
                broken.append(f"{where} (no such heading)")
    assert not broken, "\n".join(broken)


def _commands(page: Path) -> list[str]:
    """The `ccdata` / `ccfit` command lines of `page`'s shell blocks: continuation lines joined,
    comments dropped, optional parts (`[--private]`) taken as given."""
    out = []
    for block in re.findall(r"```bash\n(.*?)```", page.read_text(), flags=re.S):
        for line in re.sub(r"\\\n\s*", " ", block).splitlines():
            line = line.split(" #")[0].strip().replace("[", "").replace("]", "")
            if line.startswith(("ccdata ", "ccfit ")):
                out.append(line)
    return out


# What a command may need that the tests' empty LeRobot cache (tests/conftest.py) lacks: the
# command parsed, and stopped at the suite's dataset.
NEEDS_A_DATASET = ("no dataset of suite", "needs the seed dataset's demonstrations")


def _parse(argv: list[str]):
    """`argv` parsed as its console script does, up to (not including) running it: the config
    of a config command (None for the others)."""
    import ccdata.cli
    import ccfit.cli
    from ccfit.cli import BRANCHING, QUIET, SCRATCH_ROOT, _parse_config
    from ccfit.config import CurriculumConfig, TaskRunConfig
    from ccfit.models import DEFAULT_MODEL
    from ccfit.offline.config import OfflineConfig
    from ccfit.sweep.cli import DEFAULT_OFFLINE_MODEL
    from ccfit.sweep.cli import build_parser as sweep_parser
    from ccfit.sweep.grid import Grid, expand

    script, name = argv[0], argv[1]
    if script == "ccdata" or name not in ccfit.cli.CONFIG_COMMANDS:
        cli = ccdata.cli if script == "ccdata" else ccfit.cli
        args = cli.build_parser().parse_args(argv[1:])
        assert args.command == name
        return None
    if name == "sweep":
        args, run_args = sweep_parser().parse_known_args(argv[2:])
        if not args.status:
            offline = args.track == "offline"
            models = args.models or ((DEFAULT_OFFLINE_MODEL if offline else DEFAULT_MODEL),)
            expand(Grid(args.suites, models, args.methods, args.seeds, args.preset,
                        tuple(run_args), args.plugins, args.track), "runs/docs-sweep")  # fmt: skip
        return None
    cls = {"train": TaskRunConfig, "run": CurriculumConfig, "fit": OfflineConfig}[name]
    cfg, _ = _parse_config(cls, argv[2:], f"ccfit {name}", QUIET | SCRATCH_ROOT | BRANCHING)
    return cfg


def test_every_documented_command_parses(tmp_path, monkeypatch):
    """Each command of the README's and docs/' shell blocks names a real subcommand with real
    options and values (a config command's whole config tree is resolved and validated); a
    `--config_path` shown is where one of the documented runs saves its config."""
    from ccfit.cli import run_dir
    from ccfit.models.encoders import build_encoder, save_encoder
    from ccfit.models.tdmpc2 import TDMPC2Config

    commands = [(page, line) for page in PAGES for line in _commands(page)]
    tour = {" ".join(shlex.split(line)[:2]) for page, line in commands if page == README}
    assert {"ccdata generate", "ccfit train", "ccfit run", "ccfit report", "ccfit sweep"} <= tour
    monkeypatch.chdir(tmp_path)  # `frozen:enc.safetensors` is a file here
    enc = TDMPC2Config.preset("smoke", obs_mode="pixels", image_size=64)
    save_encoder(build_encoder(enc), enc, tmp_path / "enc.safetensors")
    failed = []
    # those reading a saved config last, once the other runs have saved theirs
    for page, line in sorted(commands, key=lambda c: "--config_path" in c[1]):
        argv = shlex.split(line)
        if "--help" in argv:
            continue
        try:
            cfg = _parse(argv)
        except BaseException as e:  # argparse's exit, ConfigError, InputError
            if not any(need in str(e) for need in NEEDS_A_DATASET):
                why = "argparse refused it (stderr)" if isinstance(e, SystemExit) else repr(e)
                failed.append(f"{page.relative_to(ROOT)}: {line}\n    {why}")
            continue
        if argv[1] == "run" and cfg is not None and not cfg.out:
            run_dir(cfg).mkdir(parents=True, exist_ok=True)
            cfg.save(run_dir(cfg) / "config.json")
    assert not failed, "\n".join(failed)
