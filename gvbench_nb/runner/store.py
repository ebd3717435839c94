"""A crash- and concurrency-safe key -> arrays store: a folder of HDF5 shards, each written under a
temporary name, fsynced and renamed, so a killed run loses only its buffer and no two writers share a
file. hloc keeps one HDF5 file a conf; we keep one folder a conf."""

from __future__ import annotations

import contextlib
import io
import json
import os
import socket
import uuid
import zlib
from collections import OrderedDict
from collections.abc import Iterable, Mapping
from pathlib import Path
from urllib.parse import quote

import h5py
import numpy as np

from gvbench_nb import GVBenchError
from gvbench_nb.io_utils import WRITE_FAILURES, fsync_folder

SHARD_SUFFIX = ".v3.h5"  # a shard of another layout is not listed (recomputed), not read as damaged
# In temporary names, so a writer only ever cleans up after dead writers of its own host.
_HOST = quote(socket.gethostname(), safe="") or "host"


class StoreCorruptError(GVBenchError, OSError):
    """A committed shard cannot be read, or its bytes no longer match their checksums."""


class StoreWriteError(GVBenchError, OSError):
    """A shard could not be written (disk full, quota, file size limit); nothing of it is kept."""


# A shard: every entry's arrays, one after another, in one byte dataset, and one JSON table of
# entries (attributes, and each array's offset, dtype, shape and CRC-32), itself checked by a CRC-32
# attribute: one read a shard for a sequence's counts, and one HDF5 dataset a shard to write (a
# dataset an array cost a quarter of a millisecond each). CRC-32 catches damage, not tampering
# (whoever can rewrite the cache can rewrite the results).
_ENTRIES = "entries"
_DATA = "data"
_ENTRIES_DIGEST = "_entries_digest"


def array_digest(array: np.ndarray) -> str:
    """CRC-32 of an array's dtype, shape and bytes (8 hex digits)."""
    array = np.ascontiguousarray(array)
    crc = zlib.crc32(f"{array.dtype.str}{array.shape}".encode())
    return f"{zlib.crc32(array.data.cast('B') if array.nbytes else b'', crc):08x}"


def _text_digest(text: bytes) -> str:
    """CRC-32 of an entries table's bytes (8 hex digits)."""
    return f"{zlib.crc32(text):08x}"


def _plain(value: object) -> object:
    """An attribute value as JSON holds it (numpy scalars become Python numbers)."""
    return value.item() if isinstance(value, np.generic) else value


def _corrupt(shard: Path, folder: Path, what: str) -> StoreCorruptError:
    return StoreCorruptError(
        f"shard {shard} of the store {folder} is damaged ({what}). Delete that file; "
        "the entries it held are recomputed by the next run"
    )


class ShardedStore:
    """A folder of HDF5 shards; every entry is a key with a few named arrays."""

    def __init__(self, folder: str | os.PathLike[str], max_open: int = 16):
        self.folder = Path(folder)
        self._index: dict[str, Path] | None = None
        # Shards open for reading, least recently read first; bounded so a long sequence holds few.
        self.max_open = max_open
        self._open: OrderedDict[Path, tuple[h5py.File, dict[str, dict]]] = OrderedDict()

    # -- reading -----------------------------------------------------------------
    def shards(self) -> list[Path]:
        return sorted(p for p in self.folder.glob(f"*{SHARD_SUFFIX}") if not p.name.startswith("."))

    def refresh(self) -> None:
        """Re-list the committed shards (other processes may have added some)."""
        self.close()
        index: dict[str, Path] = {}
        for shard in self.shards():
            # Committed shards are complete (fsync then rename): one that cannot be read was damaged since.
            for key in self._opened(shard)[1]:
                index.setdefault(key, shard)
        self._index = index

    @property
    def index(self) -> dict[str, Path]:
        if self._index is None:
            self.refresh()
        assert self._index is not None
        return self._index

    def keys(self) -> list[str]:
        return list(self.index)

    def __contains__(self, key: str) -> bool:
        return key in self.index

    def __len__(self) -> int:
        return len(self.index)

    def read(self, key: str, fields: Iterable[str] | None = None) -> dict[str, np.ndarray]:
        """One entry: its arrays (only ``fields`` when given) and its attributes as ``attr:NAME``."""
        try:
            shard = self.index[key]
        except KeyError:
            raise KeyError(f"{key!r} is not in the store {self.folder}") from None
        handle, table = self._opened(shard)
        if key not in table:
            raise _corrupt(shard, self.folder, f"entry {key!r} is not in its entries table")
        arrays = table[key]["arrays"]
        wanted = list(arrays) if fields is None else [n for n in fields if n in arrays]
        entry: dict[str, np.ndarray] = {}
        try:
            sizes = {n: int(np.prod(arrays[n][2])) * np.dtype(arrays[n][1]).itemsize for n in wanted}
            start = min((arrays[n][0] for n in wanted), default=0)
            end = max((arrays[n][0] + sizes[n] for n in wanted), default=0)
            # One read: an entry's arrays lie together.
            data = handle[_DATA][start:end].tobytes() if end > start else b""
            for name in wanted:
                offset, dtype, shape, digest = arrays[name]
                piece = data[offset - start : offset - start + sizes[name]]
                entry[name] = np.frombuffer(piece, dtype=dtype).reshape(shape).copy()
        except (OSError, KeyError, ValueError, TypeError, RuntimeError) as error:
            raise _corrupt(shard, self.folder, f"entry {key!r} cannot be read: {error}") from error
        for name, array in entry.items():
            if arrays[name][3] != array_digest(array):
                raise _corrupt(shard, self.folder, f"array {name!r} of entry {key!r} does not match its checksum")
        entry.update({f"attr:{name}": value for name, value in table[key]["attrs"].items()})
        return entry

    def _opened(self, shard: Path) -> tuple[h5py.File, dict[str, dict]]:
        """A shard's open handle and checked entries table; at most max_open stay open."""
        opened = self._open.pop(shard, None)
        if opened is None:
            try:
                handle = h5py.File(shard, "r")
                text = bytes(handle[_ENTRIES][()])
                stored = handle.attrs.get(_ENTRIES_DIGEST)
            except (OSError, KeyError, ValueError, RuntimeError) as error:
                raise _corrupt(shard, self.folder, f"its entries table cannot be read: {error}") from error
            if stored != _text_digest(text):
                handle.close()
                raise _corrupt(shard, self.folder, "its entries table does not match its checksum")
            opened = (handle, json.loads(text))
        self._open[shard] = opened
        while len(self._open) > self.max_open:
            self._open.popitem(last=False)[1][0].close()
        return opened

    def close(self) -> None:
        for handle, _ in self._open.values():
            handle.close()
        self._open.clear()

    def __del__(self) -> None:  # pragma: no cover - best effort
        with contextlib.suppress(Exception):
            self.close()

    # -- writing -----------------------------------------------------------------
    def writer(self, flush_every: int = 32) -> ShardWriter:
        self.remove_dead_temporaries()
        return ShardWriter(self, flush_every)

    def remove_dead_temporaries(self) -> list[Path]:
        """Delete half-written shards of this host's writers that are gone (live ones keep theirs)."""
        import psutil

        removed: list[Path] = []
        for path in self.folder.glob(f".shard-*.{_HOST}.tmp"):
            pid_text = path.name.split("-")[1]
            if pid_text.isdigit() and not psutil.pid_exists(int(pid_text)):
                path.unlink(missing_ok=True)
                removed.append(path)
        return removed


class ShardWriter:
    """Buffers entries and commits them atomically as one shard every ``flush_every``."""

    def __init__(self, store: ShardedStore, flush_every: int = 32):
        self.store = store
        self.flush_every = max(1, flush_every)
        self._buffer: dict[str, tuple[Mapping[str, np.ndarray], Mapping[str, object]]] = {}

    def put(self, key: str, arrays: Mapping[str, np.ndarray], attrs: Mapping[str, object] | None = None) -> None:
        self._buffer[key] = (arrays, attrs or {})
        if len(self._buffer) >= self.flush_every:
            self.flush()

    def flush(self) -> Path | None:
        if not self._buffer:
            return None
        folder = self.store.folder
        folder.mkdir(parents=True, exist_ok=True)
        name = f"shard-{os.getpid()}-{uuid.uuid4().hex[:12]}"
        temporary = folder / f".{name}.{_HOST}.tmp"
        final = folder / f"{name}{SHARD_SUFFIX}"
        # Built in memory, written with plain file I/O: a failed write is one OSError naming the file
        # (HDF5 on disk can cascade or crash). The temporary is opened first, for cleanup when killed.
        buffer = io.BytesIO()
        try:
            with open(temporary, "wb") as stream:
                with h5py.File(buffer, "w") as handle:
                    table, chunks, offset = {}, [], 0
                    for key, (arrays, attrs) in self._buffer.items():
                        placed = {}
                        for array_name, array in arrays.items():
                            array = np.ascontiguousarray(array)  # numeric: read back from these bytes
                            placed[array_name] = [offset, array.dtype.str, list(array.shape), array_digest(array)]
                            chunks.append(array.tobytes())
                            offset += array.nbytes
                        table[key] = {"attrs": {n: _plain(v) for n, v in attrs.items()}, "arrays": placed}
                    handle.create_dataset(_DATA, data=np.frombuffer(b"".join(chunks), dtype=np.uint8))
                    text = json.dumps(table).encode()
                    handle.create_dataset(_ENTRIES, data=np.void(text))
                    handle.attrs[_ENTRIES_DIGEST] = _text_digest(text)
                stream.write(buffer.getbuffer())
                stream.flush()
                os.fsync(stream.fileno())
            os.replace(temporary, final)
            fsync_folder(folder)
        except BaseException as error:
            temporary.unlink(missing_ok=True)
            if isinstance(error, OSError) and error.errno is not None:  # the file system's, not HDF5's
                advice = (
                    "free disk space (or raise the quota or file size limit)"
                    if error.errno in WRITE_FAILURES
                    else "make the folder writable"
                )
                raise StoreWriteError(
                    f"cannot write the shard {temporary} of the store {folder} "
                    f"({error.strerror or error}, {buffer.getbuffer().nbytes:,} bytes); {advice} "
                    "and run again: the entries written before it are kept"
                ) from error
            raise
        index = self.store._index
        if index is not None:
            for key in self._buffer:
                index.setdefault(key, final)
        self._buffer.clear()
        return final

    def __enter__(self) -> ShardWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        # Commit what is finished even when the loop raised: a rerun resumes from it.
        self.flush()
