"""A small Hugging Face Hub protocol server on loopback, for tests.

It implements the subset of the Hub HTTP API that `huggingface_hub` 1.x uses to create a
repository, upload a folder in one commit (regular files inline, large or binary files through
the git-LFS batch API with "basic" transfers), tag a revision, list refs and trees, and download
files (`/resolve/`). Repositories live in a temporary directory: file contents are stored once
by hash, commits are full snapshots of the tree identified by a sha1.

Auth mirrors the Hub: an unknown token is rejected (401) on every request, writes need a token
(401 without one) that has the "write" role (403 for a "read" token), private repos are readable
only with a valid token. Every request is recorded in `HubServer.requests`.
"""

from __future__ import annotations

import base64
import fnmatch
import hashlib
import hmac
import json
import os
import threading
from dataclasses import dataclass, field
from datetime import UTC, datetime
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, unquote, urlsplit

import yaml

# Repo types as they appear in API paths ("/api/datasets/...") and in file URLs ("/datasets/...").
_API_TYPES = {"models": "model", "datasets": "dataset", "spaces": "space"}
_URL_PREFIX = {"model": "", "dataset": "datasets/", "space": "spaces/"}

# Files the Hub stores through LFS in a new repo: a trimmed copy of its default .gitattributes.
_GITATTRIBUTES = "".join(
    f"{pattern} filter=lfs diff=lfs merge=lfs -text\n"
    for pattern in (
        "*.arrow",
        "*.bin",
        "*.gz",
        "*.mp4",
        "*.npy",
        "*.npz",
        "*.parquet",
        "*.pkl",
        "*.png",
        "*.pt",
        "*.safetensors",
        "*.tar",
        "*.jpg",
        "*.zip",
    )
)
# Above this size the Hub always asks for LFS, whatever .gitattributes says.
_LFS_MIN_SIZE = 10 * 1024 * 1024


def git_blob_sha1(data: bytes) -> str:
    """The git object id of a blob (what the Hub reports as a regular file's oid)."""
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


def _lfs_pointer(sha256: str, size: int) -> bytes:
    text = f"version https://git-lfs.github.com/spec/v1\noid sha256:{sha256}\nsize {size}\n"
    return text.encode()


def _now() -> str:
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%S.000Z")


@dataclass(frozen=True)
class Entry:
    """One file of a commit's tree."""

    oid: str
    """git sha1 of the stored blob (for LFS files: of the pointer file, as git would store it)."""
    size: int
    """Size of the file content in bytes."""
    sha256: str | None = None
    """sha256 of the content for LFS files, None for regular (inline) files."""


@dataclass
class Commit:
    """A full snapshot of a repository."""

    oid: str
    """sha1 identifying the commit."""
    parent: str | None
    """The previous commit on the branch, None for the first one."""
    message: str
    """The commit summary."""
    tree: dict[str, Entry]
    """path -> file."""
    date: str = field(default_factory=_now)
    """Creation time, in the Hub's ISO format."""


@dataclass
class Repo:
    """A repository: commits, branches and tags."""

    type: str
    """"model", "dataset" or "space"."""
    id: str
    """namespace/name."""
    private: bool
    """Private repos are visible only with a valid token."""
    commits: dict[str, Commit] = field(default_factory=dict)
    """oid -> commit."""
    branches: dict[str, str] = field(default_factory=dict)
    """branch name -> commit oid."""
    tags: dict[str, str] = field(default_factory=dict)
    """tag name -> commit oid."""
    created: str = field(default_factory=_now)
    """Creation time, in the Hub's ISO format."""


class _HttpError(Exception):
    """An HTTP error reply, raised inside request handling."""

    def __init__(self, status: int, message: str, code: str | None = None, headers=None):
        super().__init__(message)
        self.status, self.message, self.code = status, message, code
        self.headers = dict(headers or {})


@dataclass
class Reply:
    """A response to send."""

    status: int
    body: bytes = b""
    headers: dict[str, str] = field(default_factory=dict)


def _json(obj, status: int = 200, headers=None) -> Reply:
    hdrs = {"Content-Type": "application/json", **(headers or {})}
    return Reply(status, json.dumps(obj).encode(), hdrs)


class HubState:
    """Repositories, blob storage and tokens; thread-safe request handling."""

    def __init__(self, storage: Path, tokens: dict[str, str]):
        for role in tokens.values():
            if role not in ("read", "write"):
                raise ValueError(f"token role {role!r}: valid roles are 'read', 'write'")
        self.tokens = dict(tokens)
        self.repos: dict[tuple[str, str], Repo] = {}
        self.requests: list[dict] = []
        self._git = storage / "git"
        self._lfs = storage / "lfs"
        self._git.mkdir(parents=True, exist_ok=True)
        self._lfs.mkdir(parents=True, exist_ok=True)
        self._lock = threading.RLock()
        self._secret = os.urandom(16)

    # ---- storage -------------------------------------------------------------------------

    def _put_git(self, data: bytes) -> str:
        oid = git_blob_sha1(data)
        path = self._git / oid
        if not path.exists():
            tmp = path.with_suffix(f".{threading.get_ident()}.tmp")
            tmp.write_bytes(data)
            tmp.replace(path)
        return oid

    def _has_lfs(self, sha256: str, size: int) -> bool:
        path = self._lfs / sha256
        return path.is_file() and path.stat().st_size == size

    def read(self, entry: Entry) -> bytes:
        """The content of a file."""
        path = (self._lfs / entry.sha256) if entry.sha256 else (self._git / entry.oid)
        return path.read_bytes()

    def _sign(self, sha256: str) -> str:
        return hmac.new(self._secret, sha256.encode(), hashlib.sha256).hexdigest()

    # ---- auth ----------------------------------------------------------------------------

    def _role(self, headers) -> str | None:
        auth = headers.get("Authorization") or ""
        if not auth:
            return None
        token = auth.removeprefix("Bearer ").strip()
        if token not in self.tokens:
            raise _HttpError(401, "Invalid credentials in Authorization header")
        return self.tokens[token]

    @staticmethod
    def _require_write(role: str | None) -> None:
        if role is None:
            raise _HttpError(401, "You must be authenticated to write to the Hub")
        if role != "write":
            raise _HttpError(403, "You don't have the rights to write to this repo (read token)")

    def _repo(self, rtype: str, repo_id: str, role: str | None) -> Repo:
        repo = self.repos.get((rtype, repo_id))
        if repo is None or (repo.private and role is None):
            raise _HttpError(404 if role else 401, "Repository not found", "RepoNotFound")
        return repo

    @staticmethod
    def _resolve(repo: Repo, rev: str) -> Commit:
        oid = repo.branches.get(rev) or repo.tags.get(rev) or (rev if rev in repo.commits else None)
        if oid is None:
            raise _HttpError(404, f"Invalid rev id: {rev}", "RevisionNotFound")
        return repo.commits[oid]

    # ---- dispatch ------------------------------------------------------------------------

    def handle(self, method: str, target: str, headers, body: bytes, base: str) -> Reply:
        """Route one request; `base` is this server's URL as the client reached it."""
        parts = urlsplit(target)
        query = parse_qs(parts.query)
        seg = [unquote(s) for s in parts.path.split("/")[1:]]
        with self._lock:
            self.requests.append(
                {"method": method, "path": parts.path, "host": headers.get("Host")}
            )
        try:
            role = self._role(headers)
            with self._lock:
                return self._route(method, seg, query, headers, body, base, role)
        except _HttpError as err:
            hdrs = {"X-Error-Message": err.message, **err.headers}
            if err.code:
                hdrs["X-Error-Code"] = err.code
            return _json({"error": err.message}, err.status, hdrs)

    def _route(self, method, seg, query, headers, body, base, role) -> Reply:
        if seg[:1] == ["api"]:
            return self._route_api(method, seg[1:], query, body, base, role)
        if seg[:1] == ["lfs-upload"] and method == "PUT" and len(seg) == 2:
            return self._lfs_put(seg[1], query, body)
        if seg[:1] == ["lfs-verify"] and method == "POST" and len(seg) == 2:
            return self._lfs_verify(seg[1], query, body)
        # File URLs: [datasets/|spaces/]ns/name/resolve/rev/path... and ns/name.git/info/lfs/...
        rtype = _API_TYPES.get(seg[0] if seg else "", None)
        rest = seg[1:] if rtype and rtype != "model" else seg
        rtype = rtype if rtype and rtype != "model" else "model"
        if len(rest) >= 5 and rest[2] == "resolve" and method in ("GET", "HEAD"):
            repo = self._repo(rtype, f"{rest[0]}/{rest[1]}", role)
            return self._resolve_file(repo, rest[3], "/".join(rest[4:]), headers, method)
        if (
            len(rest) == 6
            and rest[1].endswith(".git")
            and rest[2:] == ["info", "lfs", "objects", "batch"]
        ):
            repo_id = f"{rest[0]}/{rest[1].removesuffix('.git')}"
            return self._lfs_batch(self._repo(rtype, repo_id, role), json.loads(body), base, role)
        raise _HttpError(404, f"Not found: {method} /{'/'.join(seg)}")

    def _route_api(self, method, seg, query, body, base, role) -> Reply:
        if seg == ["repos", "create"] and method == "POST":
            return self._create_repo(json.loads(body), base, role)
        if seg == ["validate-yaml"] and method == "POST":
            return self._validate_yaml(json.loads(body))
        if seg == ["whoami-v2"] and method == "GET":
            if role is None:
                raise _HttpError(401, "Invalid username or password.")
            return _json(
                {
                    "type": "user",
                    "name": "tester",
                    "auth": {"type": "access_token", "accessToken": {"role": role}},
                }
            )
        if len(seg) < 3 or seg[0] not in _API_TYPES:
            raise _HttpError(404, f"Not found: /api/{'/'.join(seg)}")
        rtype, repo_id, op, args = _API_TYPES[seg[0]], f"{seg[1]}/{seg[2]}", seg[3:4], seg[4:]
        repo = self._repo(rtype, repo_id, role)
        match (method, op, len(args)):
            case ("GET", [], 0):
                return self._info(repo, "main", query)
            case ("GET", ["revision"], 1):
                return self._info(repo, args[0], query)
            case ("GET", ["refs"], 0):
                return self._refs(repo)
            case ("GET", ["tree"], n) if n >= 1:
                return self._tree(repo, args[0], "/".join(args[1:]), query)
            case ("POST", ["paths-info"], 1):
                return self._paths_info(repo, args[0], parse_qs(body.decode()))
            case ("POST", ["preupload"], 1):
                self._require_write(role)
                return self._preupload(repo, args[0], json.loads(body))
            case ("POST", ["commit"], 1):
                self._require_write(role)
                return self._commit(repo, args[0], body, base)
            case ("POST", ["tag"], 1):
                self._require_write(role)
                return self._create_tag(repo, args[0], json.loads(body))
            case ("DELETE", ["tag"], 1):
                self._require_write(role)
                if repo.tags.pop(args[0], None) is None:
                    raise _HttpError(404, f"Tag {args[0]} not found", "RevisionNotFound")
                return _json({})
        raise _HttpError(404, f"Not found: {method} /api/{'/'.join(seg)}")

    # ---- repos ---------------------------------------------------------------------------

    def _create_repo(self, payload: dict, base: str, role) -> Reply:
        self._require_write(role)
        rtype = payload.get("type") or "model"
        if rtype not in _URL_PREFIX:
            raise _HttpError(400, f"Invalid repo type {rtype!r}")
        if not payload.get("organization"):
            raise _HttpError(400, "This server needs an explicit namespace (organization)")
        repo_id = f"{payload['organization']}/{payload['name']}"
        url = f"{base}/{_URL_PREFIX[rtype]}{repo_id}"
        if (rtype, repo_id) in self.repos:
            return _json({"error": "You already created this repo", "url": url}, 409)
        private = payload.get("visibility", "public") != "public" or bool(payload.get("private"))
        repo = Repo(rtype, repo_id, private)
        # Like the Hub: a new repo starts with one commit holding .gitattributes.
        data = _GITATTRIBUTES.encode()
        tree = {".gitattributes": Entry(self._put_git(data), len(data))}
        self._add_commit(repo, "main", tree, "initial commit")
        self.repos[(rtype, repo_id)] = repo
        return _json({"url": url, "name": repo_id})

    def _add_commit(self, repo: Repo, branch: str, tree: dict[str, Entry], message: str) -> Commit:
        parent = repo.branches.get(branch)
        listing = json.dumps([parent, message, sorted((p, e.oid) for p, e in tree.items())])
        commit = Commit(hashlib.sha1(listing.encode()).hexdigest(), parent, message, dict(tree))
        repo.commits[commit.oid] = commit
        repo.branches[branch] = commit.oid
        return commit

    def _info(self, repo: Repo, rev: str, query) -> Reply:
        commit = self._resolve(repo, rev)
        blobs = query.get("blobs", ["false"])[0].lower() in ("1", "true")
        siblings = []
        for path, entry in sorted(commit.tree.items()):
            sib = {"rfilename": path}
            if blobs:
                sib.update(size=entry.size, blobId=entry.oid)
                if entry.sha256:
                    sib["lfs"] = {
                        "size": entry.size,
                        "sha256": entry.sha256,
                        "pointerSize": len(_lfs_pointer(entry.sha256, entry.size)),
                    }
            siblings.append(sib)
        return _json(
            {
                "_id": hashlib.sha1(repo.id.encode()).hexdigest()[:24],
                "id": repo.id,
                "author": repo.id.split("/")[0],
                "sha": commit.oid,
                "private": repo.private,
                "gated": False,
                "disabled": False,
                "downloads": 0,
                "likes": 0,
                "tags": [],
                "createdAt": repo.created,
                "lastModified": commit.date,
                "siblings": siblings,
            }
        )

    def _refs(self, repo: Repo) -> Reply:
        def refs(kind, mapping):
            return [
                {"name": n, "ref": f"refs/{kind}/{n}", "targetCommit": oid}
                for n, oid in sorted(mapping.items())
            ]

        return _json(
            {
                "branches": refs("heads", repo.branches),
                "tags": refs("tags", repo.tags),
                "converts": [],
                "pullRequests": [],
            }
        )

    def _create_tag(self, repo: Repo, rev: str, payload: dict) -> Reply:
        commit = self._resolve(repo, rev)
        tag = payload.get("tag") or ""
        if not tag:
            raise _HttpError(400, "Missing tag name")
        if tag in repo.tags:
            raise _HttpError(409, f"Tag {tag} already exists")
        repo.tags[tag] = commit.oid
        return _json({"name": tag, "ref": f"refs/tags/{tag}", "targetCommit": commit.oid})

    # ---- listing -------------------------------------------------------------------------

    def _file_json(self, path: str, entry: Entry) -> dict:
        item = {"type": "file", "oid": entry.oid, "size": entry.size, "path": path}
        if entry.sha256:
            item["lfs"] = {
                "oid": entry.sha256,
                "size": entry.size,
                "pointerSize": len(_lfs_pointer(entry.sha256, entry.size)),
            }
        return item

    @staticmethod
    def _dir_json(commit: Commit, path: str) -> dict:
        oid = hashlib.sha1(f"{commit.oid}:{path}".encode()).hexdigest()
        return {"type": "directory", "oid": oid, "size": 0, "path": path}

    def _tree(self, repo: Repo, rev: str, path: str, query) -> Reply:
        commit = self._resolve(repo, rev)
        recursive = query.get("recursive", ["false"])[0].lower() in ("1", "true")
        prefix = f"{path.strip('/')}/" if path.strip("/") else ""
        files = {p: e for p, e in commit.tree.items() if p.startswith(prefix)}
        if prefix and not files:
            raise _HttpError(404, f"{path} does not exist on {rev}", "EntryNotFound")
        items, dirs = [], set()
        for p, entry in sorted(files.items()):
            rel = p[len(prefix) :].split("/")
            # Every folder between `prefix` and the file; only the first level if not recursive.
            for depth in range(1, len(rel) if recursive else min(2, len(rel))):
                dirs.add(prefix + "/".join(rel[:depth]))
            if recursive or len(rel) == 1:
                items.append(self._file_json(p, entry))
        items += [self._dir_json(commit, d) for d in sorted(dirs)]
        return _json(sorted(items, key=lambda item: item["path"]))

    def _paths_info(self, repo: Repo, rev: str, form: dict) -> Reply:
        commit = self._resolve(repo, rev)
        out = []
        for path in form.get("paths", []):
            path = path.strip("/")
            if path in commit.tree:
                out.append(self._file_json(path, commit.tree[path]))
            elif any(p.startswith(path + "/") for p in commit.tree):
                out.append(self._dir_json(commit, path))
        return _json(out)

    # ---- upload --------------------------------------------------------------------------

    @staticmethod
    def _lfs_patterns(commit: Commit, read) -> list[str]:
        entry = commit.tree.get(".gitattributes")
        if entry is None:
            return []
        lines = read(entry).decode().splitlines()
        return [ln.split()[0] for ln in lines if "filter=lfs" in ln.split()[1:]]

    def _preupload(self, repo: Repo, rev: str, payload: dict) -> Reply:
        commit = self._resolve(repo, rev)
        patterns = self._lfs_patterns(commit, self.read)
        files = []
        for f in payload.get("files", []):
            path, size = f["path"], int(f["size"])
            sample = base64.b64decode(f.get("sample", ""))
            name = path.rsplit("/", 1)[-1]
            lfs = (
                size >= _LFS_MIN_SIZE
                or b"\0" in sample
                or any(fnmatch.fnmatch(path if "/" in pat else name, pat) for pat in patterns)
            )
            item = {"path": path, "uploadMode": "lfs" if lfs else "regular", "shouldIgnore": False}
            if path in commit.tree:
                entry = commit.tree[path]
                item["oid"] = entry.sha256 or entry.oid
            files.append(item)
        return _json({"files": files, "commitOid": commit.oid})

    def _lfs_batch(self, repo: Repo, payload: dict, base: str, role) -> Reply:
        if payload.get("operation") != "upload":
            raise _HttpError(400, "Only the upload operation is supported")
        self._require_write(role)
        objects = []
        for obj in payload.get("objects", []):
            oid, size = obj["oid"], int(obj["size"])
            item = {"oid": oid, "size": size, "authenticated": True}
            if not self._has_lfs(oid, size):
                sig = self._sign(oid)
                item["actions"] = {
                    "upload": {"href": f"{base}/lfs-upload/{oid}?size={size}&sig={sig}"},
                    "verify": {"href": f"{base}/lfs-verify/{oid}?sig={sig}"},
                }
            objects.append(item)
        return _json({"transfer": "basic", "objects": objects})

    def _check_sig(self, sha256: str, query) -> None:
        if not hmac.compare_digest(query.get("sig", [""])[0], self._sign(sha256)):
            raise _HttpError(403, "Invalid or missing upload signature")

    def _lfs_put(self, sha256: str, query, body: bytes) -> Reply:
        self._check_sig(sha256, query)
        if hashlib.sha256(body).hexdigest() != sha256 or len(body) != int(query["size"][0]):
            raise _HttpError(400, "Uploaded content does not match its oid or size")
        path = self._lfs / sha256
        tmp = path.with_suffix(f".{threading.get_ident()}.tmp")
        tmp.write_bytes(body)
        tmp.replace(path)
        return Reply(200, b"", {"ETag": f'"{hashlib.md5(body).hexdigest()}"'})

    def _lfs_verify(self, sha256: str, query, body: bytes) -> Reply:
        self._check_sig(sha256, query)
        size = int(json.loads(body)["size"])
        if not self._has_lfs(sha256, size):
            raise _HttpError(404, f"LFS object {sha256} not found")
        return _json({"success": True})

    def _commit(self, repo: Repo, rev: str, body: bytes, base: str) -> Reply:
        if rev not in repo.branches:
            raise _HttpError(404, f"Branch {rev} not found", "RevisionNotFound")
        head = repo.commits[repo.branches[rev]]
        tree = dict(head.tree)
        summary = "commit"
        for line in body.splitlines():
            if not line.strip():
                continue
            op = json.loads(line)
            key, value = op["key"], op["value"]
            if key == "header":
                summary = value.get("summary") or summary
                parent = value.get("parentCommit")
                if parent is not None and parent != head.oid:
                    raise _HttpError(412, "A commit has happened since. Please refresh.")
            elif key == "file":
                if value.get("encoding") != "base64":
                    raise _HttpError(400, "Only base64 file content is supported")
                data = base64.b64decode(value["content"])
                tree[value["path"]] = Entry(self._put_git(data), len(data))
            elif key == "lfsFile":
                sha, size = value["oid"], int(value["size"])
                if not self._has_lfs(sha, size):
                    raise _HttpError(422, f"LFS object {sha} was not uploaded")
                tree[value["path"]] = Entry(git_blob_sha1(_lfs_pointer(sha, size)), size, sha)
            elif key == "deletedFile":
                if tree.pop(value["path"], None) is None:
                    raise _HttpError(404, "A file with this name doesn't exist", "EntryNotFound")
            elif key == "deletedFolder":
                prefix = value["path"].strip("/") + "/"
                tree = {p: e for p, e in tree.items() if not p.startswith(prefix)}
            else:
                raise _HttpError(400, f"Unsupported commit operation {key!r}")
        commit = self._add_commit(repo, rev, tree, summary)
        url = f"{base}/{_URL_PREFIX[repo.type]}{repo.id}/commit/{commit.oid}"
        return _json(
            {
                "success": True,
                "commitOid": commit.oid,
                "commitUrl": url,
                "hookOutput": "",
                "pullRequestUrl": None,
            }
        )

    @staticmethod
    def _validate_yaml(payload: dict) -> Reply:
        content = payload.get("content", "")
        if not content.startswith("---"):
            return _json({"errors": [], "warnings": [{"message": "Empty yaml metadata"}]})
        block = content.split("---", 2)[1] if content.count("---") >= 2 else ""
        try:
            meta = yaml.safe_load(block)
        except yaml.YAMLError as err:
            return _json({"errors": [{"message": f"Invalid YAML: {err}"}], "warnings": []}, 400)
        if meta is not None and not isinstance(meta, dict):
            return _json({"errors": [{"message": "not a mapping"}], "warnings": []}, 400)
        return _json({"errors": [], "warnings": []})

    # ---- download ------------------------------------------------------------------------

    def _resolve_file(self, repo: Repo, rev: str, path: str, headers, method: str) -> Reply:
        commit = self._resolve(repo, rev)
        entry = commit.tree.get(path)
        if entry is None:
            raise _HttpError(404, "Entry not found", "EntryNotFound", {"X-Repo-Commit": commit.oid})
        data = self.read(entry)
        hdrs = {
            "X-Repo-Commit": commit.oid,
            "Content-Type": "application/octet-stream",
            "Accept-Ranges": "bytes",
            "ETag": f'"{entry.sha256 or entry.oid}"',
        }
        if entry.sha256:
            hdrs.update({"X-Linked-Etag": f'"{entry.sha256}"', "X-Linked-Size": str(entry.size)})
        status = 200
        rng = headers.get("Range") or ""
        if method == "GET" and rng.startswith("bytes="):
            start_s, _, end_s = rng[len("bytes=") :].partition("-")
            start = int(start_s or 0)
            end = min(int(end_s), len(data) - 1) if end_s else len(data) - 1
            if start >= len(data):
                raise _HttpError(
                    416, "Range not satisfiable", headers={"Content-Range": f"bytes */{len(data)}"}
                )
            hdrs["Content-Range"] = f"bytes {start}-{end}/{len(data)}"
            data, status = data[start : end + 1], 206
        return Reply(status, data, hdrs)


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    server: _Server
    timeout = 30  # drop idle keep-alive connections

    def log_message(self, format, *args):  # noqa: A002 - silence per-request stderr lines
        pass

    def _body(self) -> bytes:
        if self.headers.get("Transfer-Encoding", "").lower() == "chunked":
            chunks = []
            while (size := int(self.rfile.readline().split(b";")[0].strip() or b"0", 16)) > 0:
                chunks.append(self.rfile.read(size))
                self.rfile.readline()
            while self.rfile.readline() not in (b"\r\n", b"\n", b""):
                pass  # trailers
            return b"".join(chunks)
        length = int(self.headers.get("Content-Length") or 0)
        return self.rfile.read(length) if length else b""

    def _serve(self) -> None:
        body = self._body() if self.command in ("POST", "PUT", "DELETE") else b""
        host, port = self.server.server_address[:2]
        base = f"http://{self.headers.get('Host') or f'{host}:{port}'}"
        reply = self.server.state.handle(self.command, self.path, self.headers, body, base)
        self.send_response(reply.status)
        for key, value in reply.headers.items():
            self.send_header(key, value)
        self.send_header("Content-Length", str(len(reply.body)))
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(reply.body)

    do_GET = do_HEAD = do_POST = do_PUT = do_DELETE = _serve


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    state: HubState


class HubServer:
    """A running hub on 127.0.0.1 at a free port; use as a context manager or call close()."""

    def __init__(self, storage: Path, tokens: dict[str, str]):
        self.state = HubState(Path(storage), tokens)
        self._httpd = _Server(("127.0.0.1", 0), _Handler)
        self._httpd.state = self.state
        self.port = self._httpd.server_address[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self._thread = threading.Thread(
            target=self._httpd.serve_forever, daemon=True, kwargs={"poll_interval": 0.05}
        )
        self._thread.start()

    def token(self, role: str) -> str:
        """A token this server accepts with `role` ("read" or "write")."""
        for token, token_role in self.state.tokens.items():
            if token_role == role:
                return token
        roles = sorted(set(self.state.tokens.values()))
        raise ValueError(f"no {role!r} token configured; configured roles: {roles}")

    @property
    def requests(self) -> list[dict]:
        """Every request received so far: method, path, host."""
        return list(self.state.requests)

    def close(self) -> None:
        self._httpd.shutdown()
        self._httpd.server_close()
        self._thread.join(timeout=5)

    def __enter__(self) -> HubServer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
