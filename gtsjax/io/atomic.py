"""One way to write a file, which every writer of a whole file uses: it appears complete or not at all.

What is written goes to ``NAME.part`` beside the target, is flushed to the disk, and is renamed over
the target only once whole, so a crash, a full disk or Ctrl-C never leaves a half-written file under
the target's name (and never a ``.part`` either). A new file gets the permissions ``open`` gives one
(0666 less the user's umask); a file written over keeps the permission bits it had, as an editor keeps
them, rather than the temporary file's.
"""

import contextlib
import os
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import IO


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb", **open_kwargs) -> Iterator[IO]:
    """``with atomic_write(path) as f: f.write(...)``: ``f`` is the temporary file, opened with ``mode``
    (``"wb"`` or ``"w"``, and ``open``'s keywords); renamed over ``path`` when the block ends normally,
    removed when it raises."""
    if "w" not in mode:
        raise ValueError(f"atomic_write writes a file anew; mode {mode!r} does not")
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    try:
        with open(tmp, mode, **open_kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        with contextlib.suppress(OSError):  # no file there yet (or one we cannot stat): open's mode stands
            os.chmod(tmp, stat.S_IMODE(os.stat(path).st_mode))
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
