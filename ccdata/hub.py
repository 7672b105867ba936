"""Publish a local LeRobot v3 dataset to a Hugging Face Hub compatible endpoint, and fetch it back.

Only the configured endpoint is ever contacted:

- Xet storage is disabled. With `hf_xet` installed, `huggingface_hub` would otherwise upload
  and download through a separate content-addressed storage host.
- Telemetry is disabled. Besides extra user-agent fields it lets `huggingface_hub` fetch an
  "agent harness" registry from its import-time default endpoint, not from ours.
- Dataset cards are never checked with `RepoCard.validate` (it posts to a hard-coded host); the
  only metadata check is `HfApi`'s own `validate-yaml` call, which goes to the endpoint.

`huggingface_hub` reads these switches from the environment once, when it is first imported, but
its functions look them up on `huggingface_hub.constants` at call time. So this module sets the
environment variables before importing it (covers child processes and a first import) and pins
the constants again before every operation (covers a process that imported it earlier).
"""

from __future__ import annotations

import os
import re
from contextlib import contextmanager
from pathlib import Path

from ccdata.dataset_format import CODEBASE_VERSION, read_codebase_version
from ccdata.errors import InputError
from ccdata.repo_id import validate_repo_id

os.environ["HF_HUB_DISABLE_XET"] = "1"
os.environ["HF_HUB_DISABLE_TELEMETRY"] = "1"

import httpx  # noqa: E402
import yaml  # noqa: E402
from huggingface_hub import HfApi, constants, get_token, snapshot_download  # noqa: E402
from huggingface_hub.errors import (  # noqa: E402
    HfHubHTTPError,
    OfflineModeIsEnabled,
    RepositoryNotFoundError,
    RevisionNotFoundError,
)

DEFAULT_TIMEOUT = 30.0
"""Seconds to wait for the endpoint's first answer before calling it unreachable."""

# Files of a local dataset root that are not part of the dataset: LeRobot's temporary frame
# images, and huggingface_hub's download bookkeeping when the root came from snapshot_download.
_IGNORE = ["images/", ".cache/**", "**/.cache/**"]


class HubError(Exception):
    """A hub operation failed; the message is one line meant for the user."""


def resolve_endpoint(endpoint: str | None = None) -> str:
    """The endpoint to use: the argument, else `HF_ENDPOINT` now, else the public Hub."""
    url = (endpoint or os.environ.get("HF_ENDPOINT") or constants._HF_DEFAULT_ENDPOINT).rstrip("/")
    if not re.fullmatch(r"https?://[^/\s]+(/\S*)?", url):
        raise HubError(f"endpoint {url!r} is not an http(s) URL")
    try:
        httpx.URL(url)
    except httpx.InvalidURL as exc:  # passes the pattern, e.g. an unclosed IPv6 bracket
        raise HubError(f"endpoint {url!r} is not a valid URL: {exc}") from None
    return url


def _pin_isolation() -> None:
    # See the module docstring: huggingface_hub consults these attributes at call time.
    constants.HF_HUB_DISABLE_XET = True
    constants.HF_HUB_DISABLE_TELEMETRY = True


def _one_line(text: str, secret: str | None) -> str:
    text = " ".join(str(text).split())
    return text.replace(secret, "***") if secret else text


def _chain(exc: BaseException):
    """`exc` and the exceptions it was raised from (huggingface_hub wraps transport errors)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ or exc.__context__


@contextmanager
def _hub_errors(endpoint: str, repo_id: str, token: str | None, action: str):
    """Turn transport and HTTP failures into a one-line HubError (never showing the token)."""
    try:
        yield
    except HubError:
        raise
    except Exception as exc:  # classified below, re-raised as is if unknown
        if isinstance(exc, ValueError) and "README.md" in str(exc):
            # HfApi checks the card's YAML header with the endpoint before uploading anything.
            raise HubError(f"cannot {action}: {_one_line(exc, token)}") from None
        for cause in _chain(exc):
            if isinstance(cause, OfflineModeIsEnabled):
                raise HubError(
                    f"cannot {action}: huggingface_hub offline mode is on (HF_HUB_OFFLINE=1)"
                ) from None
            if isinstance(cause, httpx.TimeoutException):
                raise HubError(
                    f"cannot reach the hub endpoint {endpoint}: no answer in time while trying to "
                    f"{action}"
                ) from None
            if isinstance(cause, (httpx.ConnectError, httpx.NetworkError)):
                reason = _one_line(cause, token) or type(cause).__name__
                raise HubError(f"cannot reach the hub endpoint {endpoint}: {reason}") from None
            if isinstance(cause, HfHubHTTPError) and cause.response is not None:
                raise HubError(_http_message(cause, endpoint, repo_id, token, action)) from None
        raise


def _http_message(err: HfHubHTTPError, endpoint: str, repo_id: str, token, action: str) -> str:
    status = err.response.status_code
    if isinstance(err, RepositoryNotFoundError):
        # The Hub answers a missing repo and a private one the same way.
        hidden = "" if status == 404 else " (or it is private and the token cannot read it)"
        return f"cannot {action}: dataset {repo_id} not found on {endpoint}{hidden}"
    if status == 401:
        who = "no token was sent" if token is None else "the token was rejected"
        return (
            f"cannot {action}: {endpoint} answered 401 Unauthorized ({who}); set HF_TOKEN or run "
            "`hf auth login` with a valid token"
        )
    if status == 403:
        return (
            f"cannot {action}: {endpoint} answered 403 Forbidden; the token lacks the rights "
            f"needed for {repo_id} (a write token is needed to push)"
        )
    if isinstance(err, RevisionNotFoundError):
        return f"cannot {action}: {repo_id} has no such revision on {endpoint}"
    if status == 404:
        return f"cannot {action}: dataset {repo_id} not found on {endpoint}"
    detail = err.server_message or err.response.reason_phrase
    return f"cannot {action}: {endpoint} answered HTTP {status}: {_one_line(detail, token)}"


def _check_local_dataset(root: Path) -> None:
    try:
        version = read_codebase_version(root)
    except InputError as err:
        raise HubError(f"no LeRobot dataset to push at {root}: {err}") from None
    if version != CODEBASE_VERSION:
        raise HubError(
            f"{root} is a LeRobot {version} dataset; only {CODEBASE_VERSION} can be pushed"
        )


def _check_card(root: Path) -> None:
    # Checked locally so a broken card fails before the repo is created (the endpoint checks
    # it again when the folder is uploaded).
    card = root / "README.md"
    if not card.is_file():
        return
    try:
        lines = card.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError as exc:
        raise HubError(f"{card} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    if not lines or lines[0].strip() != "---":
        return
    end = next((i for i, line in enumerate(lines[1:], 1) if line.strip() == "---"), None)
    if end is None:
        raise HubError(f"{card}: the YAML header opened by '---' is never closed")
    try:
        meta = yaml.safe_load("\n".join(lines[1:end]))
    except yaml.YAMLError as exc:
        raise HubError(f"{card}: invalid YAML header: {_one_line(exc, None)}") from None
    if meta is not None and not isinstance(meta, dict):
        raise HubError(f"{card}: the YAML header must be a mapping, got {type(meta).__name__}")


def push_dataset(
    root: Path | str,
    repo_id: str,
    endpoint: str | None = None,
    private: bool = False,
    token: str | None = None,
    timeout: float = DEFAULT_TIMEOUT,
) -> str:
    """Publish the LeRobot v3 dataset at `root` as the Hub dataset `repo_id`; return its URL.

    Creates the repo if needed, uploads the folder (data, videos, meta and the `README.md` card)
    as one commit that also removes remote files no longer present locally, and points the tag
    `v3.0` at that commit. Re-pushing unchanged data creates no commit and keeps the tag.
    The token defaults to huggingface_hub's usual sources (`HF_TOKEN`, the saved login).
    """
    try:
        validate_repo_id(repo_id)
    except ValueError as exc:
        raise HubError(f"invalid repo id: {exc}") from None
    root = Path(root).expanduser()
    _check_local_dataset(root)
    _check_card(root)
    endpoint = resolve_endpoint(endpoint)
    token = token or get_token()
    _pin_isolation()
    api = HfApi(endpoint=endpoint, token=token or False)

    with _hub_errors(endpoint, repo_id, token, f"push {repo_id}"):
        # A cheap read with a timeout first, so a dead endpoint fails fast with a clear message
        # (the upload calls themselves have no timeout and retry with backoff).
        try:
            api.dataset_info(repo_id, timeout=timeout)
        except RepositoryNotFoundError:
            pass  # a new dataset; rights are checked by create_repo below
        if token is None:
            raise HubError(
                f"cannot push {repo_id}: no Hugging Face token found; set HF_TOKEN or run "
                "`hf auth login`"
            )
        url = api.create_repo(repo_id, repo_type="dataset", private=private, exist_ok=True)
        commit = api.upload_folder(
            repo_id=repo_id,
            repo_type="dataset",
            folder_path=root,
            commit_message=f"Upload LeRobot {CODEBASE_VERSION} dataset",
            ignore_patterns=list(_IGNORE),
            delete_patterns="*",
        )
        _tag_head(api, repo_id, commit.oid)
    return str(url)


def _tag_head(api: HfApi, repo_id: str, head: str) -> None:
    # LeRobot's readers resolve the revision named by their codebase version.
    tags = {t.name: t.target_commit for t in api.list_repo_refs(repo_id, repo_type="dataset").tags}
    if tags.get(CODEBASE_VERSION) == head:
        return
    if CODEBASE_VERSION in tags:
        api.delete_tag(repo_id, tag=CODEBASE_VERSION, repo_type="dataset")
    api.create_tag(repo_id, tag=CODEBASE_VERSION, revision=head, repo_type="dataset")


def download_dataset(
    repo_id: str,
    endpoint: str | None = None,
    root: Path | str | None = None,
    token: str | None = None,
) -> Path:
    """Fetch the Hub dataset `repo_id` (tag `v3.0`, else `main`) and return its local root.

    Without `root` the files go to LeRobot's revision-safe snapshot cache
    (`$HF_LEROBOT_HOME/hub`), the same place `LeRobotDataset(repo_id)` downloads to; with `root`
    they are materialized in that folder. Pass the result as `LeRobotDataset(repo_id, root=...)`.
    If the endpoint cannot be reached, a complete cached copy is returned instead.
    """
    try:
        validate_repo_id(repo_id)
    except ValueError as exc:
        raise HubError(f"invalid repo id: {exc}") from None
    endpoint = resolve_endpoint(endpoint)
    token = token or get_token()
    _pin_isolation()
    if root is None:
        from lerobot.utils.constants import HF_LEROBOT_HUB_CACHE

        target = {"cache_dir": HF_LEROBOT_HUB_CACHE}
    else:
        root = Path(root).expanduser()
        # huggingface_hub also records the resolved refs in a cache folder; keep that
        # bookkeeping inside `root` (beside its own .cache/huggingface/download) instead of the
        # user's global hub cache.
        target = {"local_dir": root, "cache_dir": root / ".cache" / "huggingface" / "hub"}

    with _hub_errors(endpoint, repo_id, token, f"download {repo_id}"):
        for revision in (CODEBASE_VERSION, "main"):
            try:
                path = snapshot_download(
                    repo_id,
                    repo_type="dataset",
                    revision=revision,
                    endpoint=endpoint,
                    token=token or False,
                    **target,
                )
                break
            except RevisionNotFoundError:
                if revision == "main":
                    raise
    path = Path(path)
    if not (path / "meta" / "info.json").is_file():
        raise HubError(f"{repo_id} on {endpoint} is not a LeRobot dataset (no meta/info.json)")
    return path
