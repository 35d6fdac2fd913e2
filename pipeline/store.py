"""The zarr v3 store's codec: arrays written in packs or appended as record arrays, each
checked against the checksum written with it. Where a run puts what, and which groups are
done, is :mod:`workflows.store`.

**Packs.** :func:`write_arrays` writes the arrays of one call as one zarr array, a *pack*:
a (B, R) uint8 array whose B rows are byte planes of its members (R the longest member's
rows), stored as one shard (``<pack>/0.0``) whose inner chunks are the planes, each
compressed with zstd. A member fills its planes in the layout (:data:`LAYOUTS`) that
compresses best on its first rows: byte k of every row in plane k (a byte shuffle: the
exponent bytes of float32 and the high bytes of sorted ids almost vanish), each column in
turn (float64 coordinates), or the bytes as they are (probabilities). So a write is two
files (metadata and shard) in one directory whatever it holds; reading one array reads
only its planes. The logical names stay: :func:`read_array` finds an array's pack in the
group's attributes. Coordinates stay float64 and every value is stored exactly.

Every array records the CRC-32 of its values in its pack's attributes (``members``) when it
is written, and :func:`read_array` checks it: a file that disappeared (which zarr would read
as fill values) or changed is a :class:`DamagedArrayError` (a :class:`StoreError`), never
silently wrong data; it names the group and the array, so that the run's store can clear
the marks that claimed the group complete. Chunks are compressed with zstd's own frame
checksum too, and the shard index carries a CRC-32C.
"""

import zlib
from pathlib import Path

import numcodecs
import numpy as np
import zarr
from zarr.codecs import ZstdCodec

from pipeline.errors import StoreError

SCHEMA_VERSION = 7  # 3: packs of byte planes in one shard per write; parts removed once
# assembled; 4: a flag per point whose features are undefined, chunks classified in one pass;
# 5: a terrain model per scene; 6: a part's core and halo points as one record array each;
# 7: a scene's terrain blocks beside its terrain model, the position of each cell minimum,
# each tile's box as its points were read
CHECKSUM = "crc32"
#: Rows of the zarr chunks of an appended array: its first write's rows, within these bounds.
MIN_APPEND_CHUNK, MAX_APPEND_CHUNK = 1 << 14, 1 << 18
_COMPRESSOR = ZstdCodec(level=0, checksum=True)
_ZSTD = numcodecs.Zstd(level=0)  # to choose a layout on a sample
_FLAT_KEYS = {"name": "v2", "separator": "."}  # a pack's shard is <pack>/0.0: no directories



class DamagedArrayError(StoreError):
    """An array that is missing, was never completely written or whose values differ from
    what was written: ``group`` (the zarr group) and ``name`` (the array) say which."""

    def __init__(self, message: str, group: zarr.Group, name: str):
        super().__init__(message)
        self.group, self.name = group, name

    def __reduce__(self):  # pickled as the StoreError it is: a worker's error reaches the client
        return StoreError, (str(self),)


def open_store(path: str | Path, mode: str = "a") -> zarr.Group:
    """Open (or create, with mode "a"/"w") the run's store."""
    path = Path(path)
    if mode == "r" and not path.exists():
        raise StoreError(f"no store at {path}; run 'silva ingest' (or 'silva run') first")
    try:
        root = zarr.open_group(str(path), mode=mode)
        version = root.attrs.get("schema_version")
    except (ValueError, TypeError, KeyError, UnicodeDecodeError) as err:  # unreadable zarr.json
        raise StoreError(f"store {path} is damaged (its metadata cannot be read: "
                         f"{type(err).__name__}); rerun with --overwrite") from None
    except FileNotFoundError:
        raise StoreError(f"no store at {path}; run 'silva ingest' (or 'silva run') "
                         "first") from None
    if version is None and mode != "r":
        root.attrs["schema_version"] = SCHEMA_VERSION
    elif version is not None and version != SCHEMA_VERSION:
        raise StoreError(
            f"store {path} has schema version {version}, this Silva writes {SCHEMA_VERSION}; "
            "rerun with --overwrite"
        )
    return root


def checksum(data: np.ndarray, previous: int = 0) -> int:
    """CRC-32 of an array's values (continuing ``previous``: rows appended in order)."""
    return zlib.crc32(np.ascontiguousarray(data).view(np.uint8).reshape(-1), previous)


def write_arrays(group: zarr.Group, arrays: dict[str, np.ndarray], pack: str | None = None
                 ) -> None:
    """Write (replacing) whole arrays into a group as one pack named ``pack`` (by default
    the first array's name); each array keeps its name, dtype and shape for :func:`read_array`.
    """
    if not arrays:
        return
    pack = pack or next(iter(arrays))
    arrays = {name: np.ascontiguousarray(data) for name, data in arrays.items()}
    widths = {name: (data.nbytes // len(data) if len(data) else
                     data.dtype.itemsize * int(np.prod(data.shape[1:])))
              for name, data in arrays.items()}
    n_planes = sum(widths.values())
    n_rows = max(len(data) for data in arrays.values())
    planes = np.zeros((n_planes, n_rows), dtype=np.uint8)
    members, plane = {}, 0
    for name, data in arrays.items():
        width, layout = widths[name], _layout(data)
        if len(data):
            planes[plane:plane + width, :len(data)] = _to_planes(data, layout)
        members[name] = {"dtype": data.dtype.str, "shape": list(data.shape), "plane": plane,
                         "layout": layout, CHECKSUM: checksum(data)}
        plane += width
    shape = (max(n_planes, 1), max(n_rows, 1))
    group.create_array(pack, data=planes, chunks=(1, shape[1]), shards=shape, overwrite=True,
                       compressors=_COMPRESSOR, chunk_key_encoding=_FLAT_KEYS,
                       attributes={"members": members})
    index = dict(group.attrs.get("arrays", {}))
    index.update({name: pack for name in arrays})
    group.update_attributes({"arrays": index})


#: How a member's bytes fill its planes (each plane is compressed on its own):
#: ``bytes``, byte k of every row in plane k (a byte shuffle: sorted ids, float32 features);
#: ``columns``, the bytes of each column in turn (float64 coordinates, whose low bytes are
#: noise in any order); ``rows``, the bytes as they lie (probabilities: few distinct rows).
LAYOUTS = ("bytes", "columns", "rows")
_SAMPLE_ROWS = 1 << 15


def _layout(data: np.ndarray) -> str:
    """The layout whose planes compress best, judged on the first rows."""
    if len(data) < 2:
        return LAYOUTS[0]
    sample = data[:_SAMPLE_ROWS]
    sizes = [len(_ZSTD.encode(np.ascontiguousarray(_to_planes(sample, layout))))
             for layout in LAYOUTS]
    return LAYOUTS[int(np.argmin(sizes))]


def _to_planes(data: np.ndarray, layout: str) -> np.ndarray:
    """(width, n) uint8 planes of ``data`` (n rows of width bytes) in ``layout``."""
    n = len(data)
    rows = data.reshape(n, -1)
    if layout == "bytes":
        return rows.view(np.uint8).reshape(n, -1).T
    if layout == "columns":
        return np.ascontiguousarray(rows.T).view(np.uint8).reshape(-1, n)
    return rows.view(np.uint8).reshape(-1, n)


def _from_planes(planes: np.ndarray, layout: str, dtype, shape) -> np.ndarray:
    """The inverse of :func:`_to_planes`."""
    n = shape[0]
    if layout == "bytes":
        return np.ascontiguousarray(planes.T).view(dtype).reshape(shape)
    values = np.ascontiguousarray(planes).reshape(-1).view(dtype)
    if layout == "columns":
        return np.ascontiguousarray(values.reshape(-1, n).T).reshape(shape)
    return values.reshape(shape)


def _member(group: zarr.Group, name: str):
    """(pack array, description of ``name`` in it) or None when no pack holds ``name``."""
    pack = group.attrs.get("arrays", {}).get(name)
    if pack is None:
        return None
    try:
        array = group[pack]
    except KeyError:
        return None
    member = array.attrs.get("members", {}).get(name)
    return None if member is None else (array, member)


class Appender:
    """Appends rows to *record arrays* of groups, creating them on first use; :meth:`seal`
    then records each array's checksum and returns the rows each holds, as read back from
    the store, by ``(group path, array name)``. An array not sealed reads as damaged.

    A record array holds the rows of several arrays of equal length side by side: one
    uint8 (n, W) zarr array whose row k holds the bytes of row k of every member (attribute
    ``members``), read back by :func:`read_records`. These are ingest's parts, which the
    features step reads once and then removes: one array per part instead of one per
    member, since every zarr array costs a few file operations whatever its size. Rows are
    held in memory until ``hold_rows`` of them wait (or the seal), so that a small part is
    written once, in zarr chunks of its own size: a chunk much longer than its rows costs
    its whole length to encode at every write.
    """

    def __init__(self, hold_rows: int = 1 << 20):
        self.hold_rows = hold_rows
        self._arrays: dict[tuple[str, str], list] = {}  # -> [group, array, crc, rows, members]
        self._held: dict[tuple[str, str], list[np.ndarray]] = {}
        self._held_rows = 0

    def append(self, group: zarr.Group, name: str, arrays: dict[str, np.ndarray]) -> None:
        """Append the rows of ``arrays`` (member name -> array, all of one length) to the
        record array ``name`` of ``group``."""
        record, members = _record(arrays)
        entry = self._arrays.setdefault((group.path, name), [group, None, 0, 0, members])
        if entry[4] != members:
            raise ValueError(f"record array '{name}' of {group.path} has members {entry[4]}, "
                             f"not {members}")
        entry[2] = checksum(record, entry[2])
        entry[3] += len(record)
        self._held.setdefault((group.path, name), []).append(record)
        self._held_rows += len(record)
        if self._held_rows >= self.hold_rows:
            self._write_held()

    def _write_held(self) -> None:
        for key, held in self._held.items():
            entry = self._arrays[key]
            data = np.concatenate(held)
            if entry[1] is None:
                entry[1] = _record_array(entry[0], key[1], data, {"members": entry[4]})
            else:
                entry[1].append(data)
        self._held, self._held_rows = {}, 0

    def seal(self) -> dict[tuple[str, str], tuple[int, int]]:
        """Record the checksums; return {(group, name): (rows appended, rows stored)}."""
        rows = {}
        for key, (group, array, crc, appended, members) in self._arrays.items():
            held = self._held.pop(key, [])
            if array is None:  # every row still held: written once, with its checksum
                array = _record_array(group, key[1], np.concatenate(held),
                                      {"members": members, CHECKSUM: crc})
            else:
                if held:
                    array.append(np.concatenate(held))
                array.update_attributes({CHECKSUM: crc})
            stored = zarr.open_array(store=array.store, path=array.path, mode="r").shape[0]
            rows[key] = (appended, stored)
        self._held_rows = 0
        return rows


def _record(arrays: dict[str, np.ndarray]) -> tuple[np.ndarray, dict]:
    """The rows of ``arrays`` side by side as one uint8 (n, W) matrix, and its members:
    name -> [dtype, shape of a row, first byte]."""
    columns, members, start = [], {}, 0
    n = len(next(iter(arrays.values())))
    for name, data in arrays.items():
        data = np.ascontiguousarray(data)
        if len(data) != n:
            raise ValueError(f"record member '{name}' has {len(data)} rows, not {n}")
        columns.append(data.reshape(n, -1).view(np.uint8).reshape(n, -1))
        members[name] = [data.dtype.str, list(data.shape[1:]), start]
        start += columns[-1].shape[1]
    return np.concatenate(columns, axis=1), members


def _record_array(group: zarr.Group, name: str, data: np.ndarray, attributes: dict):
    """A new record array ``name`` of ``group`` holding ``data``, in zarr chunks of about
    its rows (within :data:`MIN_APPEND_CHUNK` and :data:`MAX_APPEND_CHUNK`)."""
    rows = min(max(1 << max(len(data) - 1, 0).bit_length(), MIN_APPEND_CHUNK),
               MAX_APPEND_CHUNK)
    return group.create_array(name, data=data, chunks=(rows, max(data.shape[1], 1)),
                              compressors=_COMPRESSOR, attributes=attributes)


def read_records(group: zarr.Group, name: str) -> dict[str, np.ndarray]:
    """The members of the record array ``name`` (:class:`Appender`), checked against its
    checksum as :func:`read_array` checks an array."""
    record, array = _read_checked(group, name)
    members = array.attrs["members"]
    arrays = {}
    for member, (dtype, shape, start) in members.items():
        dtype = np.dtype(dtype)
        width = dtype.itemsize * int(np.prod(shape, dtype=np.int64))
        values = np.ascontiguousarray(record[:, start:start + width]).view(dtype)
        arrays[member] = values.reshape((len(record), *shape))
    return arrays


def has_array(group: zarr.Group, name: str) -> bool:
    """Whether a pack of ``group`` holds the array ``name`` (written by :func:`write_arrays`;
    a pack written again without it no longer does)."""
    return _member(group, name) is not None


def read_array(group: zarr.Group, name: str) -> np.ndarray:
    """A whole array of a group as NumPy, checked against the checksum written with it.

    A missing, unsealed or damaged array is a :class:`DamagedArrayError` that names it.
    """
    return _read_checked(group, name)[0]


def _read_checked(group: zarr.Group, name: str):
    """:func:`read_array`'s values, and the zarr array (a pack or an appended array) they
    were read from."""
    try:
        found = _member(group, name)
        if found is None:
            array, expected = group[name], None  # an appended array (a part)
        else:
            array, member = found
            expected = member[CHECKSUM]
    except KeyError:
        raise DamagedArrayError(
            f"array '{name}' missing in store group '{group.path}'; the step that writes it did "
            "not finish: run the same command again to redo it", group, name
        ) from None
    try:
        if found is None:
            data = array[...]
            expected = array.attrs.get(CHECKSUM)
        else:
            data = _unpack(array, member)
    except Exception as err:  # noqa: BLE001 - any decoding failure means damaged bytes
        problem = f"its bytes cannot be decoded ({type(err).__name__})"
    else:
        if expected is not None and checksum(data) == expected:
            return data, array
        problem = ("it was never completely written" if expected is None else
                   "its values differ from what was written: a chunk file is missing or "
                   "corrupt")
    raise DamagedArrayError(
        f"store array '{group.path}/{name}' is damaged ({problem}); its chunk is marked for "
        "recomputation: run the same command again (or start afresh with --overwrite)",
        group, name)


def _unpack(array, member: dict) -> np.ndarray:
    """The values of one member of a pack, from its byte planes."""
    dtype, shape = np.dtype(member["dtype"]), tuple(member["shape"])
    rows = shape[0]
    width = dtype.itemsize * int(np.prod(shape[1:]))
    if rows == 0 or width == 0:
        return np.zeros(shape, dtype)
    plane = member["plane"]
    return _from_planes(array[plane:plane + width, :rows], member["layout"], dtype, shape)


def rows_of(sorted_ids: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``ids`` in a chunk's ``sorted_ids`` (its gid array) and whether each is there.

    Returns int64 positions (valid only where found) and a bool mask ``found``.
    """
    if len(sorted_ids) == 0:
        return np.zeros(len(ids), np.int64), np.zeros(len(ids), bool)
    pos = np.minimum(np.searchsorted(sorted_ids, ids), len(sorted_ids) - 1)
    return pos, sorted_ids[pos] == ids
