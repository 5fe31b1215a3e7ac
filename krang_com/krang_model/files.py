"""Files a user keeps are written atomically: into a temporary file beside the target, flushed to
disk, then renamed over it. A reader sees the old file or the new one, never a partial one, and a
process killed while saving leaves the old file (or none) behind."""

import contextlib
import os
import tempfile
from pathlib import Path


@contextlib.contextmanager
def atomic_open(path, mode='w', **kwargs):
    """open() for writing that replaces `path` only when the block ends without an error.

    The folder must exist: a mistyped output path is an error, not a new folder tree."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path('.')
    if not folder.is_dir():
        raise FileNotFoundError(f'{path}: the folder {folder} does not exist')
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp', dir=folder)
    try:
        with os.fdopen(fd, mode, **kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_text(path, text):
    with atomic_open(path, 'w') as f:
        f.write(text)
    return Path(path)


def save_figure(fig, path, **kwargs):
    """matplotlib's savefig, atomically (the format from the file suffix)."""
    path = Path(path)
    with atomic_open(path, 'wb') as f:
        fig.savefig(f, format=path.suffix.lstrip('.') or 'png', **kwargs)
    return path


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask
