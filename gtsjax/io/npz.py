"""Checks on an ``.npz`` archive before NumPy reads it: every array's header is read and compared with
the bytes its member holds, so that a damaged or hostile file (a header claiming 10⁶ × 10⁶ floats)
is refused in one line instead of asking for terabytes of memory."""

import math
import os
import zipfile

import numpy as np

from ..errors import InputError


def check_npz(path: str | os.PathLike) -> None:
    """Raise :class:`InputError` naming ``path`` and the key if any ``.npy`` member's header claims
    more data than the member holds, or cannot be read. Members are read only up to their headers.
    A file that is not a zip archive passes (``np.load`` says what it is)."""
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError):
        return
    with zf:
        for info in zf.infolist():
            if not info.filename.endswith(".npy"):
                continue
            key = info.filename[:-4]
            try:
                with zf.open(info) as f:
                    version = np.lib.format.read_magic(f)
                    if version == (1, 0):
                        shape, _, dtype = np.lib.format.read_array_header_1_0(f)
                    elif version == (2, 0):
                        shape, _, dtype = np.lib.format.read_array_header_2_0(f)
                    else:
                        raise InputError(path, f"key '{key}' is in NumPy array format {version}, which gtsjax "
                                               "does not read")
                    header = f.tell()
            except InputError:
                raise
            except (ValueError, OSError, EOFError, zipfile.BadZipFile, RuntimeError) as err:
                raise InputError(path, f"key '{key}' has a damaged array header ({type(err).__name__})") from None
            if dtype.hasobject:
                continue  # the loaders refuse pickled objects with their own message
            need = math.prod(shape) * dtype.itemsize
            have = info.file_size - header
            if need > have:
                raise InputError(path, f"key '{key}' claims shape {list(shape)} of {dtype} ({need} bytes) but holds "
                                       f"{max(have, 0)} bytes: a damaged or truncated archive")
