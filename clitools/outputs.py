"""Outputs that never destroy inputs, for both command lines.

Every file a command writes follows one rule:

- an existing output is replaced only with `overwrite` (the commands' `--overwrite`);
- an output never replaces an input of the command (whatever `overwrite` says): not the same
  file, not through a symbolic or hard link, not a file inside an input folder;
- the file is written under a unique hidden temporary name in its destination folder
  (`.NAME.tmp-XXXXXXXX.SUFFIX`, the suffix kept for writers that read the format from it) and
  renamed onto its name only when whole, so a failure (a full disk, Ctrl-C) leaves nothing under
  the final name and the temporary is removed; two writers of one path never touch each other's
  temporary, and without `overwrite` the rename refuses a file that appeared meanwhile.

    with atomic_output(out, overwrite=args.overwrite, inputs=[args.checkpoint]) as tmp:
        np.savez_compressed(tmp, ...)

`atomic_folder` does the same for code that writes several files into one folder: it stages
them in a hidden folder there and moves them out when all are written. `check_name` refuses a
user-given name that would leave the folder it names something in. `KeptErrorFile` is a file
whose writes never fail, for libraries that cannot survive a failed write (HDF5).
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from io import FileIO, RawIOBase
from pathlib import Path

OVERWRITE_HELP = "replace an existing output (never an input: that is refused)"
"""The help of every command's `--overwrite`."""
NAME_CHARACTERS = "letters, digits, '_', '-' or '.' (not starting with '.')"


def check_name(name: str, what: str) -> str:
    """`name` when it can be one file or folder name under an output folder, else ValueError.

    A name from the user that becomes part of a path (a variant, a test set) must stay inside
    the folder it names something in: letters, digits, '_', '-' and '.', not starting with '.'
    (so never '..', an absolute path or a separator).

    Args:
        name: The name as given.
        what: What it names, for the message (e.g. "--test name").
    """
    if not (name and name.replace("_", "").replace("-", "").replace(".", "").isalnum() and name[0] != "."):
        raise ValueError(f"{what} {name!r} must be {NAME_CHARACTERS}: it names a file or folder under --out")
    return name


def _error(kind: type[OSError], number: int | None, message: str) -> OSError:
    """An OSError of `kind` whose text is `message` alone (no "[Errno N]" before it)."""
    err = kind(message)
    err.errno = number
    return err


FULL_DISK = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def _named(err: BaseException, output: Path, temporary: Path) -> BaseException:
    """The error of a failed write as the user should read it: naming `output`, never the
    temporary (a full disk's OSError names no file at all); `err` itself when it names a file."""
    text = str(err)
    if str(temporary) in text:
        text = text.replace(str(temporary), str(output))
    elif isinstance(err, OSError) and not err.filename and str(output) not in text:
        if getattr(err, "names_output", False):  # an inner output's error, already named
            return err
        if err.errno in FULL_DISK:
            text = f"writing {output} failed: {err.strerror or text}"
        else:  # e.g. numpy's "86880 requested and 12468 written"
            text = f"{text} (while writing {output})"
    else:
        return err
    try:
        named = type(err)(text)
    except Exception:  # an error class that wants other arguments keeps its own text
        return err
    if isinstance(err, OSError):
        named.errno = err.errno
    named.names_output = True
    return named


def _input_clash(path: Path, inputs: Iterable) -> str | None:
    """Why writing `path` would replace an input, or None."""
    target = Path(os.path.realpath(path))
    exists = os.path.lexists(path)
    via = f" (a link to {target})" if target != Path(os.path.abspath(path)) else ""
    for item in inputs:
        source = Path(os.path.realpath(item))
        if target == source:
            return f"{path}{via} is the input {item}"
        if exists and os.path.exists(item) and _same_file(path, item):
            return f"{path} is a hard link to the input {item}"
        if exists and source.is_dir() and target.is_relative_to(source):
            return f"{path}{via} lies inside the input folder {item}"
    return None


def _same_file(a, b) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:  # a dangling link
        return False


def check_output(path: str | Path, *, overwrite: bool, inputs: Iterable = ()) -> Path:
    """Refuse writing `path` (before any work is done) when it would replace an input (a
    ValueError, whatever `overwrite` says), when it is a folder, or when it exists and
    `overwrite` is false (FileExistsError); returns it as a Path.

    Args:
        path: The output file.
        overwrite: Whether an existing output may be replaced.
        inputs: Files and folders the command reads.
    """
    path = Path(path)
    clash = _input_clash(path, [Path(p) for p in inputs])
    if clash:
        raise ValueError(f"{clash}: an output never replaces an input, even with --overwrite; write it elsewhere")
    if path.is_dir():
        raise _error(IsADirectoryError, errno.EISDIR, f"{path} is a folder; give a file name for the output")
    if os.path.lexists(path) and not overwrite:
        raise _error(
            FileExistsError, errno.EEXIST, f"{path} exists; replace it with --overwrite, or choose another name"
        )
    return path


def _publish(tmp: Path, path: Path, *, overwrite: bool) -> None:
    """Rename the finished `tmp` onto `path`. Without `overwrite` a hard link makes the step
    refuse a file that appeared since the check (rename would replace it)."""
    _sync(tmp)
    if overwrite:
        os.replace(tmp, path)  # a symbolic link at `path` is replaced, never its target
        return
    try:
        os.link(tmp, path)
    except FileExistsError:
        message = f"{path} appeared while it was written; replace it with --overwrite, or choose another name"
        raise _error(FileExistsError, errno.EEXIST, message) from None
    except OSError:  # no hard links on this file system
        if os.path.lexists(path):
            raise _error(FileExistsError, errno.EEXIST, f"{path} exists; replace it with --overwrite") from None
        os.replace(tmp, path)
        return
    os.unlink(tmp)


def _sync(path: Path) -> None:
    """Flush the file to the disk, so that a write the system deferred fails here, before the rename."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _make_folder(folder: Path) -> list[Path]:
    """Create `folder` and its missing parents; returns those created, innermost first."""
    created = []
    for p in (folder, *folder.parents):
        if p.exists() or p == p.parent:
            break
        created.append(p)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise _error(type(err), err.errno, f"cannot make the folder {folder} ({err.strerror})") from None
    return created


def _remove_empty(folders: list[Path]) -> None:
    for p in folders:
        with contextlib.suppress(OSError):
            p.rmdir()


def _default_mode() -> int:
    """The mode a new file gets under the process's umask (mkstemp makes 0600)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


@contextlib.contextmanager
def atomic_output(path: str | Path, *, overwrite: bool, inputs: Iterable = ()) -> Iterator[Path]:
    """Write one output file safely: yields a new temporary path in the output's folder (with the
    output's suffix) for the caller to write; renamed onto `path` when the block ends without
    error, removed on any error (Ctrl-C included). `check_output`'s refusals come first.

    Args:
        path: The output file; its folder is made if missing (and removed again on failure).
        overwrite: Whether an existing output may be replaced.
        inputs: Files and folders the command reads; none of them is ever replaced.
    """
    inputs = [Path(p) for p in inputs]
    path = check_output(path, overwrite=overwrite, inputs=inputs)
    created = _make_folder(path.parent)
    try:
        fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.tmp-", suffix=path.suffix)
    except OSError as err:
        _remove_empty(created)
        raise _error(type(err), err.errno, f"cannot write {path} ({err.strerror})") from None
    os.close(fd)
    tmp = Path(name)
    try:
        os.chmod(tmp, _default_mode())
        yield tmp
        check_output(path, overwrite=overwrite, inputs=inputs)  # the inputs may have moved meanwhile
        _publish(tmp, path, overwrite=overwrite)
    except BaseException as err:
        tmp.unlink(missing_ok=True)
        _remove_empty(created)
        named = _named(err, path, tmp)
        if named is err:
            raise
        raise named from err


@contextlib.contextmanager
def atomic_folder(
    folder: str | Path, *, overwrite: bool, inputs: Iterable = (), expected: Iterable[str] = ()
) -> Iterator[Path]:
    """Write several files into `folder` safely: yields a new hidden staging folder inside it for
    the caller to write into (subfolders allowed); when the block ends without error every file
    written there is checked (`check_output` on its place in `folder`: all before any moves)
    and moved to that place; on any error the staging folder is removed, and `folder` too if
    this call made it.

    Args:
        folder: The output folder; made if missing.
        overwrite: Whether existing outputs may be replaced.
        inputs: Files and folders the command reads; none of them is ever replaced.
        expected: Names (relative to `folder`) the caller will write, checked before any work.
    """
    folder, inputs, expected = Path(folder), [Path(p) for p in inputs], list(expected)
    if folder.exists() and not folder.is_dir():
        raise _error(NotADirectoryError, errno.ENOTDIR, f"--out {folder} is a file; give a folder for the output")
    for name in expected:
        check_output(folder / name, overwrite=overwrite, inputs=inputs)
    created = _make_folder(folder)
    try:
        stage = Path(tempfile.mkdtemp(dir=folder, prefix=f".{folder.resolve().name or 'out'}.tmp-"))
    except OSError as err:
        _remove_empty(created)
        what = folder / expected[0] if expected else folder
        raise _error(type(err), err.errno, f"cannot write {what} ({err.strerror})") from None
    try:
        yield stage
        files = sorted(p.relative_to(stage) for p in stage.rglob("*") if not p.is_dir())
        for name in files:
            check_output(folder / name, overwrite=overwrite, inputs=inputs)
        for name in files:
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            _publish(stage / name, folder / name, overwrite=overwrite)
    except BaseException as err:
        shutil.rmtree(stage, ignore_errors=True)
        _remove_empty(created)
        named = _named(err, folder, stage)
        if named is err:
            raise
        raise named from err
    shutil.rmtree(stage, ignore_errors=True)


class KeptErrorFile(RawIOBase):
    """A file opened for writing whose writes never fail: the first OSError (a full disk) is
    kept in `error` and that write and every later one are dropped.

    HDF5 cannot survive a failed write: its file close then fails half way, and the objects left
    behind crash the process (a segmentation fault) when they are freed. Written through this
    file (`h5py.File(KeptErrorFile(path), "w")`), the library finishes and closes cleanly; the
    caller stops early by checking `error` and raises it after the close (`raise_kept`).
    """

    def __init__(self, path: str | Path):
        super().__init__()
        self.path = Path(path)
        self.error: OSError | None = None
        self._file = FileIO(self.path, "w+")

    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        return self._file.seek(offset, whence)

    def tell(self) -> int:
        return self._file.tell()

    def readinto(self, buffer) -> int:
        return self._file.readinto(buffer)

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        if self.error is None:
            try:
                done = 0
                while done < len(view):  # an unbuffered write may take part of the data
                    done += self._file.write(view[done:])
            except OSError as err:
                self.error = err
        return len(view)

    def truncate(self, size: int | None = None) -> int:
        if self.error is None:
            try:
                return self._file.truncate(size)
            except OSError as err:
                self.error = err
        return self.tell() if size is None else size

    def flush(self) -> None:
        pass  # unbuffered

    def close(self) -> None:
        if not self.closed:
            self._file.close()
        super().close()

    def raise_kept(self, output: str | Path | None = None) -> None:
        """Raise the kept error, if a write failed, naming `output` (default: this file)."""
        if self.error is not None:
            err = self.error
            raise _error(type(err), err.errno, f"writing {output or self.path} failed: {err.strerror}") from err
