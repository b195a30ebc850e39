"""Rotating msgpack recording files written by a thread of their own: one map per record.

A record is `{"k": kind, "t": t_ns, "d": data}`; every file starts with a `header` record naming
the format, its version and what the daemon ran with (docs/RECORDING.md). `write()` only appends
to a bounded queue and never waits (a full queue drops the record and counts it), so a slow or
stalled disk costs the event loop nothing. The writer thread drains the queue every
WRITE_INTERVAL_S, encodes (JPEG frames included) and appends whole batches: a crash loses at most
that much and leaves at worst a truncated last record, which the reader tolerates.

A disk that fails is a state, never an exception: a full disk keeps the file (cut back to its
last whole record) and retries the writes with backoff (FAILING); any other error closes the
file and retries opening a new one with backoff (RETRYING). `status()` says which, the last
error, and how much was written and dropped.
"""

from __future__ import annotations

import enum
import errno
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from host.recording.files import FileSystem, file_name, file_number, recording_paths

log = logging.getLogger(__name__)

FORMAT_NAME = "orbitar-recording"
FORMAT_VERSION = 2  # 2: raw link bytes, config and calibration in the header (1 had neither)
READABLE_VERSIONS = (1, 2)
BYTES_PER_MB = 1024 * 1024

# Record kinds written by the daemon (readers must skip kinds they do not know).
KIND_HEADER = "header"
KIND_LINK = "link"  # {"dir": "rx"|"tx", "bytes": raw link bytes}, t = host monotonic ns
KIND_ENCODER = "encoder"  # {"s_mm", "v_mm_s", "inputs"}, t = sample time in host ns
KIND_HEAD = "head"  # {"pan_rad", "tilt_rad"}
KIND_RANGE = "range"  # {"distance_mm", "quality"}: RANGE_SAMPLE, when ranging feeds the pose
KIND_FRAME = "frame"  # {"index", "exposure_ns", "status", "jpeg"?, "width"?, "height"?}
KIND_POSE = "pose"  # PoseSample.to_dict()
KIND_EVENT = "event"  # daemon events: link up/down, reload, reference marks, …

WRITE_INTERVAL_S = 0.1  # the thread writes what queued up this often (or sooner when half full)
LINK_CHECK_INTERVAL_S = 1.0  # how often the thread checks the open file was not deleted
RETRY_FIRST_S = 0.5
RETRY_MAX_S = 30.0
STILL_FAILING_LOG_S = 60.0  # a failing disk is logged on change, then once a minute
STALLED_AFTER_S = 2.0  # a disk call this long: status says failing (the thread cannot say it)
CLOSE_TIMEOUT_S = 0.5  # of the SIGTERM budget (2 s), after the stop ack and the link close
QUEUE_RECORDS = 50_000  # ~20 s of everything at serial rates
QUEUE_BYTES = 64 * BYTES_PER_MB
QUEUE_FRAMES = 8  # raw images waiting for JPEG encoding: frames never crowd samples out
JPEG_QUALITY = 85
RECORD_OVERHEAD_BYTES = 64  # queue accounting of a record without large fields
DISK_FULL = frozenset({errno.ENOSPC, errno.EDQUOT})


class RecordingState(enum.Enum):
    """What the recording is doing (shown in `status`)."""

    OFF = "off"  # not started, or closed
    RECORDING = "recording"  # a file is open and the last write went through
    FAILING = "failing"  # the disk is full: the file is kept, writes retried with backoff
    RETRYING = "retrying"  # no usable file: opening a new one is retried with backoff


class RecordingWriter:
    """Appends records to `dir/orbitar-NNNNNN.orec` from a thread, rotating and keeping N files."""

    def __init__(
        self,
        directory: str | Path,
        rotate_mb: float = 64.0,
        keep_files: int = 10,
        include_frames: bool = False,
        *,
        header: dict[str, Any] | Callable[[], dict[str, Any]] | None = None,
        fs: FileSystem | None = None,
        drop_when_full: bool = True,
        queue_records: int = QUEUE_RECORDS,
        queue_bytes: int = QUEUE_BYTES,
    ) -> None:
        """`header`: extra header fields, or a function giving them (called, in the writer
        thread, for every new file); `drop_when_full=False` makes `write` wait for room instead
        (offline tools, tests)."""
        self.directory = Path(directory)
        self.rotate_bytes = max(1, int(rotate_mb * BYTES_PER_MB))
        self.keep_files = keep_files
        self.include_frames = include_frames
        self.header = header if callable(header) else dict(header or {})
        self.fs = fs or FileSystem()
        self.drop_when_full = drop_when_full
        self.queue_records, self.queue_bytes = queue_records, queue_bytes
        self.state = RecordingState.OFF
        self.records = 0  # written, headers excluded
        self.bytes = 0  # appended to files by this writer, headers included
        self.frames = 0  # frame records written with their JPEG
        self.dropped_queue_full = 0  # records refused by write() (counted under the lock)
        self.dropped_unwritten = 0  # records the thread could not write (no file, disk error)
        self.errors = 0
        self.last_error = ""
        self._last_error_s: float | None = None
        self._cond = threading.Condition(threading.Lock())  # not re-entrant: cheaper
        self._queue: deque[tuple[str, int, Any, int]] = deque()
        self._queued_bytes = 0
        self._queued_frames = 0
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._fd: int | None = None
        self._path: Path | None = None
        self._number = 0
        self._size = 0
        self._retry_at = 0.0
        self._backoff_s = RETRY_FIRST_S
        self._next_check = 0.0
        self._last_log_s = 0.0
        self._busy_since: float | None = None  # the thread is in a disk call since then
        self._packer = msgpack.Packer(use_bin_type=True)

    # ---- the producer side (any thread, the event loop included) -------------------------

    def open(self) -> None:
        """Start the writer thread; it opens the first file. Never raises: see `status()`."""
        if self._thread is not None:
            return
        self.state = RecordingState.RETRYING  # until the first file is open
        self._thread = threading.Thread(target=self._run, name="recording-writer", daemon=True)
        self._thread.start()

    def write(self, kind: str, t_ns: int, data: Any) -> bool:
        """Queue one record; False (and counted) if the queue is full. Never blocks by default."""
        if self._thread is None or self._stopping:
            return False
        frame = 0
        if kind == KIND_FRAME and _has_image(data):
            if not self.include_frames:  # no image to hold in the queue, nothing to encode
                data = {k: v for k, v in data.items() if k != "image"}
            frame = int(self.include_frames)
        cost = _cost(data)
        with self._cond:
            while self._full(cost, frame):
                if self.drop_when_full or self._stopping:
                    self.dropped_queue_full += 1
                    return False
                self._cond.wait()
            self._queue.append((kind, t_ns, data, cost))
            self._queued_bytes += cost
            self._queued_frames += frame
            if self._half_full():
                self._cond.notify_all()
        return True

    def close(self, timeout_s: float = CLOSE_TIMEOUT_S) -> bool:
        """Write what is queued and close the file; False if the disk did not finish in time."""
        thread = self._thread
        if thread is None:
            return True
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        thread.join(timeout_s)
        if thread.is_alive():
            log.warning("recording writer still blocked on the disk at close; abandoned")
            return False
        self._thread = None
        return True

    @property
    def dropped(self) -> int:
        """Records that never reached a file, for any reason."""
        return self.dropped_queue_full + self.dropped_unwritten

    @property
    def current(self) -> Path | None:
        """The file being written, None when there is none (never a file that is gone)."""
        return self._path if self._fd is not None else None

    @property
    def last_file(self) -> Path | None:
        """The file opened last, open or not (after close: the one just finished)."""
        return self._path

    def files(self) -> list[Path]:
        """Recording files in the directory, oldest first."""
        return recording_paths(self.directory, self.fs)

    def status(self) -> dict[str, Any]:
        """State, file, counts and the last error, for the daemon's `status`."""
        now = time.monotonic()
        age = None if self._last_error_s is None else round(now - self._last_error_s, 3)
        waiting = self.state in (RecordingState.FAILING, RecordingState.RETRYING)
        current = self.current
        state, error = self.state.value, self.last_error
        busy = self._busy_since
        blocked_s = 0.0 if busy is None else now - busy
        if blocked_s > STALLED_AFTER_S:
            state = RecordingState.FAILING.value
            error = f"disk not answering: a write has been blocked for {blocked_s:.1f} s"
        return {
            "state": state,
            "dir": str(self.directory),
            "file": str(current) if current is not None else None,
            "bytes": self.bytes,
            "records": self.records,
            "frames": self.frames,
            "include_frames": self.include_frames,
            "dropped": self.dropped,
            "dropped_queue_full": self.dropped_queue_full,
            "queued": len(self._queue),
            "errors": self.errors,
            "last_error": error,
            "last_error_age_s": age,
            "blocked_s": round(blocked_s, 3),
            "retry_in_s": round(max(0.0, self._retry_at - now), 3) if waiting else None,
        }

    def _full(self, cost: int, frame: int) -> bool:
        """No room for one more record (caller holds the lock)."""
        return (
            len(self._queue) >= self.queue_records
            or (bool(self._queue) and self._queued_bytes + cost > self.queue_bytes)
            or (bool(frame) and self._queued_frames >= QUEUE_FRAMES)
        )

    def _half_full(self) -> bool:
        """Time to wake the writer early (caller holds the lock)."""
        records, size = len(self._queue), self._queued_bytes
        return 2 * records > self.queue_records or 2 * size > self.queue_bytes

    # ---- the writer thread ---------------------------------------------------------------

    def _run(self) -> None:
        """Drain the queue until closed; then close the file."""
        try:
            while True:
                batch, stopping = self._take()
                self._busy_since = time.monotonic()
                self._service(batch)
                self._busy_since = None
                if stopping and not self._queue:
                    break
        except Exception as exc:  # a bug must not take the daemon down: say so, stop recording
            self.last_error, self._last_error_s = (
                f"writer stopped: {_describe(exc)}",
                time.monotonic(),
            )
            log.exception("recording writer failed")
        finally:
            self._close_file()
            self.state = RecordingState.OFF

    def _take(self) -> tuple[list[tuple[str, int, Any, int]], bool]:
        """Wait up to WRITE_INTERVAL_S (less when half full or closing); take the whole queue."""
        with self._cond:
            if not self._stopping:
                self._cond.wait(WRITE_INTERVAL_S)
            batch = list(self._queue)
            self._queue.clear()
            self._queued_bytes = self._queued_frames = 0
            self._cond.notify_all()
            return batch, self._stopping

    def _service(self, batch: list[tuple[str, int, Any, int]]) -> None:
        """Make sure a file is open (retrying when due) and append the batch to it."""
        now = time.monotonic()
        if self._fd is None and now >= self._retry_at:
            self._open_file()
        if self._fd is not None and now >= self._next_check:
            self._next_check = now + LINK_CHECK_INTERVAL_S
            self._check_linked()
        if self._fd is None or (self.state is RecordingState.FAILING and now < self._retry_at):
            self.dropped_unwritten += len(batch)
            self._still_failing(now)
            return
        packed = self._encode(batch)
        self.dropped_unwritten += len(batch) - len(packed)
        while packed and self._fd is not None:
            piece = self._piece(packed)
            if self._append(b"".join(piece)):
                self.records += len(piece)
            else:
                self.dropped_unwritten += len(piece) + len(packed)  # the rest of the batch too
                packed.clear()
            if self._fd is not None and self._size >= self.rotate_bytes:
                self._close_file()
                self._open_file()
        if packed and self._fd is None:
            self.dropped_unwritten += len(packed)

    def _piece(self, packed: list[bytes]) -> list[bytes]:
        """Take from `packed` the records that fill the current file up to its rotation size.

        At least one: a file whose header alone passes the size still takes a record.
        """
        room = self.rotate_bytes - self._size
        n, taken = 0, 0
        while n < len(packed) and (n == 0 or taken < room):
            taken += len(packed[n])
            n += 1
        piece = packed[:n]
        del packed[:n]
        return piece

    def _open_file(self) -> None:
        """Open the next numbered file and write its header; RETRYING on any failure."""
        path: Path | None = None
        fd: int | None = None
        try:
            self.fs.makedirs(self.directory)
            files = recording_paths(self.directory, self.fs)
            # Never a number this writer used: a file deleted under it is not reborn by name.
            number = max(file_number(files[-1]) if files else 0, self._number) + 1
            path = self.directory / file_name(number)
            fd = self.fs.create(path)
            head = {
                "format": FORMAT_NAME,
                "version": FORMAT_VERSION,
                "unix_time": time.time(),
                "file_number": number,
                **(self.header() if callable(self.header) else self.header),
            }
            blob = self._packer.pack({"k": KIND_HEADER, "t": time.monotonic_ns(), "d": head})
            _write_all(self.fs, fd, blob)
        except (OSError, ValueError, TypeError) as exc:
            if fd is not None:
                self._discard(fd, path)
            self._fail(RecordingState.RETRYING, exc)
            return
        self._fd, self._path, self._size, self._number = fd, path, len(blob), number
        self.bytes += len(blob)
        self._next_check = time.monotonic() + LINK_CHECK_INTERVAL_S
        self._recovered()
        self._prune()

    def _append(self, blob: bytes) -> bool:
        """Append whole records; on a full disk cut the file back to them and keep it."""
        assert self._fd is not None
        try:
            _write_all(self.fs, self._fd, blob)
        except OSError as exc:
            if exc.errno in DISK_FULL and self._cut_back():
                self._fail(RecordingState.FAILING, exc)
            else:
                self._close_file()
                self._fail(RecordingState.RETRYING, exc)
            return False
        self._size += len(blob)
        self.bytes += len(blob)
        self._recovered()
        return True

    def _cut_back(self) -> bool:
        """Truncate a partly written batch away; False if even that failed."""
        assert self._fd is not None
        try:
            self.fs.truncate(self._fd, self._size)
        except OSError:
            return False
        return True

    def _check_linked(self) -> None:
        """A file deleted under us is reopened at once: status must never name a ghost."""
        assert self._fd is not None
        try:
            linked = self.fs.linked(self._fd)
        except OSError as exc:
            self._close_file()
            self._fail(RecordingState.RETRYING, exc)
            return
        if not linked:
            gone = self._path
            self._close_file()
            self._fail(RecordingState.RETRYING, FileNotFoundError(f"{gone} was deleted"))
            self._retry_at = 0.0

    def _encode(self, batch: list[tuple[str, int, Any, int]]) -> list[bytes]:
        """Pack a batch (JPEG-encoding frames); records that cannot be packed are left out."""
        out: list[bytes] = []
        for kind, t_ns, data, _ in batch:
            if kind == KIND_FRAME and isinstance(data, dict):
                data = self._frame_data(data)
            try:
                out.append(self._packer.pack({"k": kind, "t": t_ns, "d": data}))
            except (ValueError, TypeError, OverflowError) as exc:
                self._note_error(exc, f"record {kind!r} cannot be packed")
        return out

    def _frame_data(self, data: dict[str, Any]) -> dict[str, Any]:
        """A frame record: the image becomes a JPEG when frames are recorded, else goes."""
        image = data.get("image")
        out = {k: v for k, v in data.items() if k != "image"}
        if not self.include_frames:
            out.pop("jpeg", None)
            return out
        if isinstance(image, np.ndarray):
            jpeg = _jpeg(image)
            if jpeg is not None:
                out.update(jpeg=jpeg, width=int(image.shape[1]), height=int(image.shape[0]))
        if "jpeg" in out:
            self.frames += 1
        return out

    def _prune(self) -> None:
        """Delete the oldest files beyond keep_files (a failure is counted, not a state)."""
        files = self.files()
        for old in files[: max(0, len(files) - self.keep_files)]:
            try:
                self.fs.unlink(old)
            except OSError as exc:
                self._note_error(exc, "old recording not deleted")

    def _close_file(self) -> None:
        """Close the current file, if any."""
        fd, self._fd = self._fd, None
        if fd is not None:
            try:
                self.fs.close(fd)
            except OSError as exc:
                self._note_error(exc, "recording close failed")

    def _discard(self, fd: int, path: Path | None) -> None:
        """A file whose header could not be written: close and delete it (best effort)."""
        try:
            self.fs.close(fd)
            if path is not None:
                self.fs.unlink(path)
        except OSError:
            pass

    # ---- state and logging ---------------------------------------------------------------

    def _fail(self, state: RecordingState, exc: Exception) -> None:
        """Enter FAILING or RETRYING; log a change, schedule the next try with backoff."""
        message = _describe(exc)
        changed = state is not self.state or message != self.last_error
        self.errors += 1
        self.last_error, self._last_error_s = message, time.monotonic()
        self.state = state
        self._retry_at = time.monotonic() + self._backoff_s
        if changed:
            self._last_log_s = time.monotonic()
            log.error(
                "recording %s",
                state.value,
                extra={"kv": {"dir": self.directory, "error": message, "retry_s": self._backoff_s}},
            )
        self._backoff_s = min(self._backoff_s * 2, RETRY_MAX_S)

    def _recovered(self) -> None:
        """A write or an open went through: RECORDING again, backoff reset."""
        self._backoff_s = RETRY_FIRST_S
        if self.state is not RecordingState.RECORDING:
            if self.errors:
                kv = {"file": self._path, "dropped": self.dropped, "after": self.last_error}
                log.warning("recording resumed", extra={"kv": kv})
            self.state = RecordingState.RECORDING

    def _still_failing(self, now: float) -> None:
        """While the disk stays bad: one line a minute, with what was lost."""
        if now - self._last_log_s >= STILL_FAILING_LOG_S:
            self._last_log_s = now
            kv = {"state": self.state.value, "error": self.last_error, "dropped": self.dropped}
            log.warning("recording still not writing", extra={"kv": kv})

    def _note_error(self, exc: Exception, what: str) -> None:
        """An error that changes no state (a record, a prune): counted, logged on change."""
        message = f"{what}: {_describe(exc)}"
        self.errors += 1
        if message != self.last_error:
            log.error("recording: %s", message)
        self.last_error, self._last_error_s = message, time.monotonic()


def _write_all(fs: FileSystem, fd: int, blob: bytes) -> None:
    """Write every byte (os.write may write fewer); a zero-byte write is a full disk."""
    view = memoryview(blob)
    while view:
        written = fs.write(fd, view)
        if written <= 0:
            raise OSError(errno.ENOSPC, "no space left on device (wrote 0 bytes)")
        view = view[written:]


def _describe(exc: Exception) -> str:
    """An error as one line: type, errno name and message."""
    if isinstance(exc, OSError) and exc.errno is not None:
        name = errno.errorcode.get(exc.errno, str(exc.errno))
        return f"{type(exc).__name__} [{name}]: {exc.strerror or exc}"
    return f"{type(exc).__name__}: {exc}"


def _has_image(data: Any) -> bool:
    """A frame record still carrying its raw image."""
    return isinstance(data, dict) and isinstance(data.get("image"), np.ndarray)


def _cost(data: Any) -> int:
    """Queue accounting of one record: its large fields' sizes plus a fixed overhead."""
    if isinstance(data, dict):
        extra = 0
        for value in data.values():
            if isinstance(value, bytes | bytearray | memoryview):
                extra += len(value)
            elif isinstance(value, np.ndarray):
                extra += value.nbytes
        return RECORD_OVERHEAD_BYTES + extra
    return RECORD_OVERHEAD_BYTES


def _jpeg(image: np.ndarray) -> bytes | None:
    """JPEG bytes of an 8-bit image (None, and logged, if OpenCV cannot encode it)."""
    import cv2  # the writer thread pays the import, the first time only

    try:
        ok, buf = cv2.imencode(".jpg", image, [int(cv2.IMWRITE_JPEG_QUALITY), JPEG_QUALITY])
    except cv2.error as exc:
        log.warning("frame not encoded: %s", exc)
        return None
    return bytes(buf) if ok else None
