"""NumPy ``.npz`` archives, read safely (no pickles, bounded sizes) and written atomically."""
from __future__ import annotations

import io as _stdio
import zipfile

import numpy as np

from ..._files import atomic_write, read_bytes


#: The largest .npz read, and the most its arrays may hold once decompressed (2 GiB each):
#: a compressed archive can announce gigabytes in a few bytes.
MAX_NPZ_BYTES = 2**31


def read_npz(path, fields=(), *, what: str = "an .npz file") -> dict:
    """All arrays of a NumPy ``.npz`` archive, read eagerly and safely.

    Pickled objects are refused (they could run code); an archive larger than
    :data:`MAX_NPZ_BYTES`, or whose members announce more than that decompressed, is
    refused before anything is inflated.

    Parameters
    ----------
    path : str or PathLike
    fields : sequence of str
        Names that must be present.
    what : str
        What the file should be, for the messages ("an average face model").

    Returns
    -------
    dict of name -> ndarray

    Raises
    ------
    ValueError
        Naming the file: missing, not an .npz archive, corrupt, too large, pickled
        data, or lacking one of `fields`.
    """
    raw = read_bytes(path, MAX_NPZ_BYTES, what)
    where = repr(str(path))
    try:
        with zipfile.ZipFile(_stdio.BytesIO(raw)) as archive:
            announced = sum(info.file_size for info in archive.infolist())
            if announced > MAX_NPZ_BYTES:
                raise ValueError(f"{where}: its arrays would take {announced:,} bytes decompressed; "
                                 f"{what} holds at most {MAX_NPZ_BYTES:,}")
        with np.load(_stdio.BytesIO(raw), allow_pickle=False) as data:
            arrays = {name: np.asarray(data[name]) for name in data.files}
    except ValueError as exc:
        if str(exc).startswith(where):
            raise
        raise ValueError(f"{where}: not {what}: {exc}") from None
    except Exception as exc:  # zipfile, zlib and the .npy header parser raise many types
        raise ValueError(f"{where}: not {what}: corrupt .npz archive ({type(exc).__name__}: {exc})") from None
    missing = [name for name in fields if name not in arrays]
    if missing:
        raise ValueError(f"{where}: not {what}: lacks the array(s) {', '.join(missing)}")
    return arrays


def write_npz(path, **arrays) -> None:
    """Write arrays to a compressed ``.npz`` (atomically, like every writer here)."""

    buffer = _stdio.BytesIO()
    np.savez_compressed(buffer, **arrays)
    atomic_write(path, buffer.getvalue())
