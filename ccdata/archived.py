"""Which commit a source tree exported without its history was made from.

`git archive` fills in the `$Format$` fields below (`export-subst`, .gitattributes), so a
release tarball, or a snapshot a run was launched from, still says which code it is. In a
checkout they stay as written and git itself answers (`ccdata.slurm.code_version`).
"""

from __future__ import annotations

COMMIT = "$Format:%H$"
DESCRIBE = "$Format:%(describe:tags)$"
"""`git describe --tags` at archive time: empty where no tag is reachable, left as written by
a git older than 2.32."""
SHORT = "$Format:%h$"


def archived_commit() -> dict | None:
    """{'describe', 'commit'} as `git archive` wrote them, or None in a tree it did not make."""
    if COMMIT.startswith("$Format"):
        return None
    described = DESCRIBE and not DESCRIBE.startswith("$Format")
    return {"describe": DESCRIBE if described else SHORT, "commit": COMMIT}
