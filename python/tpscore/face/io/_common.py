"""What the readers of several formats share: a text file's lines, and the largest mesh
file read (by trimesh or by the OBJ parser)."""
from __future__ import annotations

from ..._files import MAX_TEXT_FILE_BYTES, read_bytes


#: The largest mesh file read (1 GiB): an OBJ of ten million vertices.
MAX_MESH_FILE_BYTES = 2**30


def _read_text(path, limit: int = MAX_TEXT_FILE_BYTES, what: str = "a landmark file") -> list[str]:
    """Lines of a text file of at most `limit` bytes, without line endings (accepts
    \\n, \\r\\n and \\r)."""
    raw = read_bytes(path, limit, what)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{str(path)!r}: not a UTF-8 text file (byte {exc.start})") from None
    return text.splitlines()
