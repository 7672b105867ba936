"""The README's Python example runs as written, and quietly (no EGL clean-up noise at exit)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


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
