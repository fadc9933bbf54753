"""Writing outputs without losing them: one live writer per output, partial names per run, checks before
simulating, atomic replacement and crate saves that roll back when they fail.

* :class:`OutputLock` -- a run holds an exclusive ``flock`` on ``.<name>.lock`` beside its output for as long
  as it writes; a second run on the same output is refused (:class:`OutputBusy`, naming the holder's pid)
  instead of deleting the first one's partial file. The kernel drops the lock when a process dies (SIGKILL
  included), so a stale lock file never blocks a later run.
* :func:`partial_path` -- a run authors ``<stem>.partial-<pid>-<start ms><ext>`` (unique also where every
  run has the same pid, as in containers); :func:`stale_partials` lists those left by runs that died (what
  ``--resume`` continues from).
* :func:`check_output` -- before anything is simulated: the output is not a folder, its folder exists or
  can be made and is writable, and the file system has room for the first frames.
* :class:`CrateRollback` -- a crate (``.usdc``) save appends to the file in place: it writes the new samples
  over the old structural sections (tokens, fields, paths, specs and the table of contents at the end of
  the file), then the new structural sections and rewrites the 88-byte bootstrap at offset 0. A save that
  fails half way (disk full, I/O error) leaves a bootstrap pointing past the end of the file. Before each
  save the bootstrap and the structural tail (a few kB) are copied; after a failed save they are written
  back and the file is truncated to its old length, so it is byte for byte the last good save. The copy is
  also written, before the save, to a journal beside the file (``.<name>.rollback``, atomically and synced)
  and removed after it: a process killed half way through a save (SIGKILL, power loss) leaves the journal,
  and :func:`recover_partial` (``--resume`` calls it) rolls the file back to its last good save.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import pathlib
import re
import shutil
import struct
import time


USD_SUFFIXES = (".usdc", ".usda", ".usd")  # files USD reads and writes (".usd": crate when written)


class CacheWriteError(OSError):
    """An output could not be written (disk full, I/O error, permission, a folder in the way); the message
    names the file and the error, and says what the last good save holds."""


class OutputBusy(CacheWriteError):
    """Another live run writes the same output."""


def usd_error_text(exc: BaseException) -> str:
    """The first useful line of a ``pxr.Tf.ErrorException`` (the root cause), without USD's internal
    namespaces; text-format parse errors as line and column."""
    notes = [str(getattr(e, "commentary", e)).strip() for e in (exc.args or (exc,))]
    notes = [n for n in notes if n and not n.startswith("Failed to open layer")]
    if not notes:  # USD gave no reason
        return "USD cannot read the layer (corrupt or truncated?)"
    msg = re.sub(r"pxrInternal_v\w+?__pxrReserved__::", "", notes[0]).strip()
    m = re.search(r"(\S*?):(\d+):(\d+): parse error matching .*? at '(.*?)'(?: in <(.*?)>)?", msg, re.S)
    if m:
        where = f" in <{m.group(5)}>" if m.group(5) else ""
        cut = ""
        if m.group(4) == "":
            cut = " (the file ends early: truncated?)"
        elif _last_line(m.group(1)) == int(m.group(2)):  # cut inside a token of its last line
            cut = " (the error is on the file's last line: truncated?)"
        elif _open_brackets(m.group(1)):  # cut inside a block: the parser names the block's start
            cut = " (the file ends inside an open bracket: truncated?)"
        return f"USD text parse error at line {m.group(2)}, column {m.group(3)}{where}{cut}"
    m = re.match(r"(\S*?):(\d+):(\d+): (.*)", msg, re.S)  # "/abs/path.usda:4:2: Expected } at '...'"
    if m:
        cut = " (the error is on the file's last line: truncated?)" if _last_line(m.group(1)) == int(m.group(2)) else ""
        msg = f"USD text error at line {m.group(2)}, column {m.group(3)}: {m.group(4)}{cut}"
    msg = " ".join(msg.split())
    return msg if len(msg) <= 300 else msg[:297] + "..."


def _open_brackets(path: str) -> bool:
    """Whether a text file ends with brackets left open (outside quoted strings): a file cut short."""
    try:
        with open(path, "rb") as f:
            text = f.read().decode("utf-8", "replace")
    except OSError:
        return False
    text = re.sub(r'"(?:[^"\\\n]|\\.)*"', "", text)  # (an unclosed string at the end is left: its brackets count)
    return sum(text.count(c) for c in "([{") > sum(text.count(c) for c in ")]}")


def _last_line(path: str) -> int | None:
    """The number of the last line of a text file (None when it cannot be read)."""
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError:
        return None
    return data.count(b"\n") + (0 if data.endswith(b"\n") else 1)


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary name next to `path` to write to; rename it to `path` when the block succeeds
    (and remove it when it fails), so a file under the final name is always complete."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_text(path, text: str):
    """Write a text file atomically (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


RUN_TAG = f"{os.getpid()}-{time.time_ns() // 1_000_000}"  # this process: pid and start time [ms]


def partial_path(path) -> pathlib.Path:
    """Where this run authors the cache that becomes `path` when it closes."""
    path = pathlib.Path(path)
    return path.with_name(f"{path.stem}.partial-{RUN_TAG}{path.suffix}")


def stale_partials(path) -> list[pathlib.Path]:
    """Partial files of `path` left by runs that are no longer alive (oldest first); a live run holds the
    output's lock, so call this while holding it."""
    path = pathlib.Path(path)
    pattern = re.compile(rf"{re.escape(path.stem)}\.partial-\d+-\d+{re.escape(path.suffix)}")
    found = [p for p in path.parent.iterdir() if pattern.fullmatch(p.name) and p != partial_path(path)]
    return sorted(found, key=lambda p: p.stat().st_mtime)


def remove_partial(path):
    """Remove a partial file and its crate journal (:class:`CrateRollback`), if any."""
    path = pathlib.Path(path)
    path.unlink(missing_ok=True)
    CrateRollback.journal_path(path).unlink(missing_ok=True)


def check_output(path, bytes_needed: int = 0) -> pathlib.Path:
    """Check before simulating that `path` can be written: not a folder, a folder that exists (or can be
    made) and is writable, `bytes_needed` free. Raises :class:`CacheWriteError` naming the problem."""
    path = pathlib.Path(path)
    if path.is_dir():
        raise CacheWriteError(f"{path}: is a folder; give a file name such as {path / 'cache.usdc'}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise CacheWriteError(f"{path}: a parent of it is a file, not a folder") from None
    except OSError as exc:
        raise CacheWriteError(f"{path}: cannot make its folder: {exc.strerror or exc}") from None
    folder = path.parent
    if not os.access(folder, os.W_OK | os.X_OK):
        raise CacheWriteError(f"{path}: the folder {folder} is not writable")
    if bytes_needed:
        free = shutil.disk_usage(folder).free
        if free < bytes_needed:
            raise CacheWriteError(f"{path}: {free / 1e6:.1f} MB free on its file system, the first frames need about "
                                  f"{bytes_needed / 1e6:.1f} MB")
    return path


class OutputLock:
    """An exclusive lock on an output for the lifetime of one writer (see the module docstring)."""

    def __init__(self, path):
        self.path = pathlib.Path(path)
        self.lock_path = self.path.with_name(f".{self.path.name}.lock")
        self.fd = None

    def acquire(self) -> "OutputLock":
        while True:
            fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "?"
                os.close(fd)
                if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise OutputBusy(f"{self.path}: another live run (pid {holder}) is writing this output; give a different "
                                     f"-o, or wait for it to finish") from None
                raise
            # The file may have been unlinked by the previous holder between our open and flock: retry on a fresh one.
            try:
                same = os.stat(self.lock_path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
                self.fd = fd
                return self
            os.close(fd)

    def release(self):
        if self.fd is None:
            return
        with contextlib.suppress(OSError):
            self.lock_path.unlink()
        os.close(self.fd)
        self.fd = None

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()
        return False


class DeferredSignals:
    """SIGINT and SIGTERM are held while the block runs and raised as KeyboardInterrupt when it ends (with
    ``raise_after=True``) or left in :attr:`pending` for the caller. For closing a cache (a rename cut half
    way loses nothing, but a close skipped does) and for third-party imports that swallow KeyboardInterrupt
    (trimesh wraps its optional imports in ``except BaseException``). Main thread only; elsewhere a no-op."""

    def __init__(self, raise_after: bool = False):
        self.raise_after = raise_after
        self.pending: list[int] = []
        self.previous: dict = {}

    def __enter__(self):
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self.previous[sig] = signal.signal(sig, lambda s, f: self.pending.append(s))
        return self

    def __exit__(self, exc_type, exc, tb):
        import signal

        for sig, handler in self.previous.items():
            signal.signal(sig, handler)
        if self.pending and self.raise_after and exc_type is None:
            raise KeyboardInterrupt
        return False


_CRATE_MAGIC = b"PXR-USDC"
_BOOTSTRAP = 88  # ident[8], version[8], tocOffset int64, reserved int64[8]
_SECTION = struct.Struct("<16sqq")  # name[16], start, size
_JOURNAL = struct.Struct("<8sBqq")  # magic, kind (0: no file, 1: bootstrap + tail, 2: whole file), size, start
_JOURNAL_MAGIC = b"CWROLLBK"


class CrateRollback:
    """What a crate save may overwrite, copied before the save (see the module docstring); :meth:`restore`
    puts it back. A file that is not a crate is copied whole; one that is not there yet is removed again."""

    def __init__(self, path):
        self.path = pathlib.Path(path)
        self.exists = self.path.exists()
        self.boot = self.tail = self.whole = None
        self.start = self.size = 0
        if not self.exists:
            return
        with open(self.path, "rb") as fh:
            self.size = os.fstat(fh.fileno()).st_size
            try:
                self.boot = fh.read(_BOOTSTRAP)
                if self.boot[:8] != _CRATE_MAGIC:
                    raise ValueError("not a crate file")
                (toc,) = struct.unpack_from("<q", self.boot, 16)
                fh.seek(toc)
                (count,) = struct.unpack("<Q", fh.read(8))
                if not 0 < count < 1000:
                    raise ValueError("implausible table of contents")
                starts = [_SECTION.unpack(fh.read(_SECTION.size))[1] for _ in range(count)]
                self.start = min(min(starts), toc)
                if not _BOOTSTRAP <= self.start <= self.size:
                    raise ValueError("section outside the file")
                fh.seek(self.start)
                self.tail = fh.read()
            except (ValueError, struct.error):
                fh.seek(0)
                self.whole, self.boot, self.tail = fh.read(), None, None

    @staticmethod
    def journal_path(path) -> pathlib.Path:
        path = pathlib.Path(path)
        return path.with_name(f".{path.name}.rollback")

    def write_journal(self):
        """Store this rollback beside the file (atomically, synced) before a save that may be cut off."""
        kind = 0 if not self.exists else (2 if self.whole is not None else 1)
        head = _JOURNAL.pack(_JOURNAL_MAGIC, kind, self.size, self.start)
        journal = self.journal_path(self.path)
        with atomic_path(journal) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(head + (self.whole if kind == 2 else (self.boot + self.tail) if kind == 1 else b""))
                fh.flush()
                os.fsync(fh.fileno())

    def discard_journal(self):
        """The save went through: sync the file, then drop the journal."""
        if self.path.exists():
            with open(self.path, "rb") as fh:
                os.fsync(fh.fileno())
        self.journal_path(self.path).unlink(missing_ok=True)

    @classmethod
    def from_journal(cls, path) -> "CrateRollback | None":
        """The rollback a cut-off save left in its journal, or None when there is none (or it is incomplete: it
        is written under a temporary name and renamed, so an incomplete one means the save had not begun)."""
        journal = cls.journal_path(path)
        try:
            data = journal.read_bytes()
        except FileNotFoundError:
            return None
        if len(data) < _JOURNAL.size or data[:8] != _JOURNAL_MAGIC:
            raise ValueError(f"{journal}: not a cloth_warp rollback journal")
        _, kind, size, start = _JOURNAL.unpack_from(data)
        body = data[_JOURNAL.size:]
        self = cls.__new__(cls)
        self.path, self.exists, self.size, self.start = pathlib.Path(path), kind != 0, size, start
        self.boot = self.tail = self.whole = None
        if kind == 1:
            self.boot, self.tail = body[:_BOOTSTRAP], body[_BOOTSTRAP:]
        elif kind == 2:
            self.whole = body
        return self

    def restore(self):
        """Make the file what it was when this rollback was taken (remove it if it did not exist)."""
        if not self.exists:
            self.path.unlink(missing_ok=True)
            return
        with open(self.path, "r+b") as fh:
            if self.whole is not None:
                fh.seek(0)
                fh.write(self.whole)
            else:
                fh.seek(self.start)
                fh.write(self.tail)
                fh.truncate(self.size)
                fh.seek(0)
                fh.write(self.boot)
            fh.truncate(self.size)
            fh.flush()
            os.fsync(fh.fileno())


def recover_partial(path, copy_to=None) -> bool:
    """Roll a partial crate file back to its last good save when a save of it was cut off (its journal is
    there: the writing process was killed during a save); returns whether there was one. Call while holding
    the output's lock (a live writer has a journal during each save); to look without writing, give
    `copy_to`: the file is copied there and the copy rolled back."""
    rollback = CrateRollback.from_journal(path)
    if rollback is None:
        return False
    if copy_to is not None:
        if rollback.exists:
            shutil.copyfile(path, copy_to)
        rollback.path = pathlib.Path(copy_to)
    rollback.restore()
    if copy_to is None:
        CrateRollback.journal_path(path).unlink(missing_ok=True)
    return True
