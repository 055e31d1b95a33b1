"""Tile message schema and its msgpack codec (DESIGN.md section 4), sparse or dense on the wire.

Wire map: ``{"v": 1, "uav", "cls", "z", "x", "y", "n", "t", "seq", "idx": bytes, "val": bytes}``;
``val`` holds uint8 quantised values (value = byte / 255), ``idx`` uint16 little-endian row-major cell
indices; without ``idx`` the ``val`` bytes are the dense n*n tile. Unknown keys are ignored (forward
compatible: producers may add optional fields); everything else is validated strictly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
from numpy.typing import ArrayLike, NDArray

from shared.messages import (
    VERSION,
    MessageError,
    check_float,
    check_int,
    check_name,
    check_uav,
    check_version,
    get_field,
    unpack_map,
)
from shared.tiles import MAX_N, MAX_ZOOM

__all__ = [
    "DEFAULT_MAX_TILE_BYTES",
    "MAX_SEQ",
    "SparseTile",
    "TileDecodeError",
    "TileMessage",
    "decode_tile",
    "decode_tile_sparse",
    "encode_tile",
    "encode_tile_sparse",
    "quantise",
]

#: Largest accepted tile payload: a sparse 256 x 256 tile listing every cell (3 bytes a cell) plus
#: header room; a dense tile is 64 KiB plus header.
DEFAULT_MAX_TILE_BYTES = 256 * 1024
#: seq is a msgpack unsigned integer (uint64).
MAX_SEQ = 2**64 - 1
_VALUE_SCALE = 255.0


class TileDecodeError(MessageError):
    """A tile payload that does not follow the schema; ``.reason`` as in ``MESSAGE_ERROR_REASONS``.

    Tile-specific reasons: "bad_zoom" (z outside 0..24), "tile_out_of_range" (x or y outside
    0..2**z - 1), "bad_n" (n outside 1..256), "bad_seq" (seq outside 0..2**64 - 1), "bad_length"
    (dense val not n*n bytes, odd idx length, idx and val of different counts),
    "index_out_of_range" (an index >= n*n), "duplicate_index". Indices need not be sorted.
    """


def _check_header(
    uav: object, cls: object, z: object, x: object, y: object, n: object, t: object, seq: object
) -> tuple[str, str, int, int, int, int, float, int]:
    uav = check_uav(uav, "uav", allow_joint=True)
    cls = check_name(cls, "cls")
    z = check_int(z, "z", 0, MAX_ZOOM, reason="bad_zoom")
    side = 1 << z
    x = check_int(x, "x", 0, side - 1, reason="tile_out_of_range")
    y = check_int(y, "y", 0, side - 1, reason="tile_out_of_range")
    n = check_int(n, "n", 1, MAX_N, reason="bad_n")
    t = check_float(t, "t")
    seq = check_int(seq, "seq", 0, MAX_SEQ, reason="bad_seq")
    return uav, cls, z, x, y, n, t, seq


@dataclass(frozen=True, slots=True, eq=False)
class TileMessage:
    """One tile of one UAV's (or the joint) memory map for one class.

    uav: UAV id, or "joint" for fused tiles. cls: class name. z, x, y: slippy-map tile (z in 0..24,
    x and y in 0..2**z - 1). n: cells along a tile edge, 1..256. t: seconds since the UNIX epoch
    (finite). seq: publisher's sequence number, 0..2**64 - 1, increasing per publisher so receivers
    can drop stale or repeated tiles. values: (n, n) float32 in [0, 1], row-major from the tile's
    north-west corner (converted to float32 if given another real dtype). Equality is identity
    (``eq=False``) because ``values`` is an array; compare fields and ``np.array_equal`` instead.
    Invalid fields raise MessageError (a ValueError) naming the field.
    """

    uav: str
    cls: str
    z: int
    x: int
    y: int
    n: int
    t: float
    seq: int
    values: np.ndarray

    def __post_init__(self) -> None:
        header = _check_header(self.uav, self.cls, self.z, self.x, self.y, self.n, self.t, self.seq)
        for name, value in zip(("uav", "cls", "z", "x", "y", "n", "t", "seq"), header, strict=True):
            object.__setattr__(self, name, value)
        values = np.asarray(self.values)
        if not (np.issubdtype(values.dtype, np.floating) or np.issubdtype(values.dtype, np.integer)):
            raise MessageError("bad_type", f"values must be real numbers, got dtype {values.dtype}", "values")
        values = values.astype(np.float32, copy=False)
        if values.shape != (self.n, self.n):
            raise MessageError("bad_length", f"values must have shape {(self.n, self.n)}, got {values.shape}", "values")
        if not np.all(np.isfinite(values)):
            raise MessageError("non_finite", "values must be finite", "values")
        if values.size and (values.min() < 0.0 or values.max() > 1.0):
            raise MessageError(
                "out_of_range", f"values must be in [0, 1], got [{values.min()}, {values.max()}]", "values"
            )
        object.__setattr__(self, "values", values)


def quantise(values: ArrayLike) -> NDArray[np.uint8]:
    """Wire quantisation of values in [0, 1]: uint8 ``round(v * 255)`` clipped to 0..255, same shape.

    The round trip error ``|byte / 255 - v|`` is at most 0.5 / 255 for v in [0, 1].
    """
    scaled = np.rint(np.asarray(values, dtype=np.float32) * np.float32(_VALUE_SCALE))
    return np.clip(scaled, 0, 255).astype(np.uint8)


def _pack_tile(header: tuple[str, str, int, int, int, int, float, int], wire: dict[str, bytes]) -> bytes:
    uav, cls, z, x, y, n, t, seq = header
    record: dict[str, Any] = {
        "v": VERSION,
        "uav": uav,
        "cls": cls,
        "z": z,
        "x": x,
        "y": y,
        "n": n,
        "t": t,
        "seq": seq,
        **wire,
    }
    return msgpack.packb(record, use_bin_type=True)


def _wire_arrays(n: int, idx: NDArray[np.int64], val: NDArray[np.uint8]) -> dict[str, bytes]:
    """Sparse fields when 3 bytes a cell beat n*n dense bytes, else the dense field."""
    if 3 * idx.size < n * n:
        return {"idx": idx.astype("<u2").tobytes(), "val": val.tobytes()}
    dense = np.zeros(n * n, dtype=np.uint8)
    dense[idx] = val
    return {"val": dense.tobytes()}


def encode_tile(msg: TileMessage) -> bytes:
    """msgpack bytes of a tile message, sparse or dense, whichever is smaller.

    Values are quantised with :func:`quantise`; the sparse form lists the cells whose byte is
    non-zero in row-major order (so a tile of zeros is an empty sparse tile, about 60 bytes).
    """
    header = (msg.uav, msg.cls, msg.z, msg.x, msg.y, msg.n, msg.t, msg.seq)
    flat = quantise(msg.values).ravel()
    idx = np.flatnonzero(flat)
    return _pack_tile(header, _wire_arrays(msg.n, idx, flat[idx]))


def encode_tile_sparse(
    uav: str,
    cls: str,
    z: int,
    x: int,
    y: int,
    n: int,
    t: float,
    seq: int,
    idx: ArrayLike,
    val: ArrayLike,
) -> bytes:
    """msgpack bytes of a tile given already quantised non-zero cells, without a dense float tile.

    idx: (k,) integer row-major cell indices in 0..n*n - 1, distinct, any order (sorted on the
    wire). val: (k,) integer bytes in 0..255 (value = byte / 255). The dense form is written instead
    when it is smaller (k >= n*n / 3). Raises MessageError (a ValueError) on bad header fields or
    arrays.
    """
    header = _check_header(uav, cls, z, x, y, n, t, seq)
    n = header[5]
    idx_arr = np.asarray(idx)
    val_arr = np.asarray(val)
    if idx_arr.ndim != 1 or val_arr.ndim != 1 or idx_arr.shape != val_arr.shape:
        raise MessageError(
            "bad_length", f"idx and val must be 1-D of equal length, got {idx_arr.shape}, {val_arr.shape}"
        )
    if idx_arr.size and not np.issubdtype(idx_arr.dtype, np.integer):
        raise MessageError("bad_type", f"idx must be integers, got dtype {idx_arr.dtype}", "idx")
    if val_arr.size and not np.issubdtype(val_arr.dtype, np.integer):
        raise MessageError("bad_type", f"val must be integers, got dtype {val_arr.dtype}", "val")
    idx_arr = idx_arr.astype(np.int64, copy=False)
    if idx_arr.size and (idx_arr.min() < 0 or idx_arr.max() >= n * n):
        raise MessageError("index_out_of_range", f"idx must be in 0..{n * n - 1}", "idx")
    if val_arr.size and (val_arr.min() < 0 or val_arr.max() > 255):
        raise MessageError("out_of_range", "val must be in 0..255", "val")
    order = np.argsort(idx_arr, kind="stable")
    idx_arr = idx_arr[order]
    if np.any(idx_arr[1:] == idx_arr[:-1]):
        raise MessageError("duplicate_index", "idx must not repeat a cell", "idx")
    return _pack_tile(header, _wire_arrays(n, idx_arr, val_arr[order].astype(np.uint8)))


def decode_tile(payload: bytes, *, max_bytes: int = DEFAULT_MAX_TILE_BYTES) -> TileMessage:
    """Parse and strictly validate a tile payload.

    payload: bytes (or bytearray / memoryview) of at most ``max_bytes``. Returns a TileMessage with
    (n, n) float32 values byte / 255 (0 for cells absent from a sparse tile). Raises only
    TileDecodeError, whose ``.reason`` says what was wrong; unknown extra keys are ignored.
    """
    record = unpack_map(payload, max_bytes, TileDecodeError)
    try:
        check_version(get_field(record, "v"))
        header = _check_header(*(get_field(record, key) for key in ("uav", "cls", "z", "x", "y", "n", "t", "seq")))
        values = _decode_values(record, header[5])
    except TileDecodeError:
        raise
    except MessageError as exc:
        raise TileDecodeError(exc.reason, str(exc), exc.field) from None
    uav, cls, z, x, y, n, t, seq = header
    # header and values are valid by construction; skip the re-validation of __post_init__
    msg = object.__new__(TileMessage)
    for name, value in zip(("uav", "cls", "z", "x", "y", "n", "t", "seq", "values"), (*header, values), strict=True):
        object.__setattr__(msg, name, value)
    return msg


@dataclass(frozen=True, slots=True, eq=False)
class SparseTile:
    """A decoded tile as its non-zero cells, the form the fusion server works in (no dense floats).

    Header fields as in :class:`TileMessage`. idx: (k,) uint16 row-major cell indices, strictly
    increasing; val: (k,) uint8 bytes, all non-zero (value = byte / 255). Built only by
    :func:`decode_tile_sparse`, which has validated them.
    """

    uav: str
    cls: str
    z: int
    x: int
    y: int
    n: int
    t: float
    seq: int
    idx: NDArray[np.uint16]
    val: NDArray[np.uint8]


def decode_tile_sparse(payload: bytes, *, max_bytes: int = DEFAULT_MAX_TILE_BYTES) -> SparseTile:
    """Parse and validate a tile payload exactly as :func:`decode_tile` does (same reasons), but
    return its non-zero cells, sorted, instead of a dense float tile: ~10 x cheaper for sparse tiles."""
    record = unpack_map(payload, max_bytes, TileDecodeError)
    try:
        check_version(get_field(record, "v"))
        header = _check_header(*(get_field(record, key) for key in ("uav", "cls", "z", "x", "y", "n", "t", "seq")))
        idx, val = _decode_sparse(record, header[5])
    except TileDecodeError:
        raise
    except MessageError as exc:
        raise TileDecodeError(exc.reason, str(exc), exc.field) from None
    return SparseTile(*header, idx, val)


def _decode_sparse(record: dict, n: int) -> tuple[NDArray[np.uint16], NDArray[np.uint8]]:
    cells = n * n
    val = get_field(record, "val")
    if not isinstance(val, bytes):
        raise TileDecodeError("bad_type", f"val must be msgpack bin, got {type(val).__name__}", "val")
    if "idx" not in record:
        if len(val) != cells:
            raise TileDecodeError("bad_length", f"dense val must have n*n = {cells} bytes, got {len(val)}", "val")
        dense = np.frombuffer(val, dtype=np.uint8)
        indices = np.flatnonzero(dense).astype(np.uint16)
        return indices, dense[indices]
    idx = record["idx"]
    if not isinstance(idx, bytes):
        raise TileDecodeError("bad_type", f"idx must be msgpack bin, got {type(idx).__name__}", "idx")
    if len(idx) % 2:
        raise TileDecodeError("bad_length", f"idx must have an even byte length, got {len(idx)}", "idx")
    if len(idx) // 2 != len(val):
        raise TileDecodeError("bad_length", f"idx has {len(idx) // 2} indices but val has {len(val)} bytes", "val")
    indices = np.frombuffer(idx, dtype="<u2").astype(np.uint16)
    values = np.frombuffer(val, dtype=np.uint8)
    ordered = indices.size < 2 or bool((indices[1:] > indices[:-1]).all())  # encoders sort
    top = (int(indices[-1]) if ordered else int(indices.max())) if indices.size else 0
    if top >= cells:
        raise TileDecodeError("index_out_of_range", f"idx holds {top}, must be < n*n = {cells}", "idx")
    if not ordered:
        order = np.argsort(indices, kind="stable")
        indices, values = indices[order], values[order]
        if bool(np.any(indices[1:] == indices[:-1])):
            raise TileDecodeError("duplicate_index", "idx repeats a cell", "idx")
    if values.size and not bool(values.all()):
        keep = values != 0
        indices, values = indices[keep], values[keep]
    return indices, values


def _decode_values(record: dict, n: int) -> NDArray[np.float32]:
    cells = n * n
    val = get_field(record, "val")
    if not isinstance(val, bytes):
        raise TileDecodeError("bad_type", f"val must be msgpack bin, got {type(val).__name__}", "val")
    if "idx" not in record:
        if len(val) != cells:
            raise TileDecodeError("bad_length", f"dense val must have n*n = {cells} bytes, got {len(val)}", "val")
        dense = np.frombuffer(val, dtype=np.uint8)
    else:
        idx = record["idx"]
        if not isinstance(idx, bytes):
            raise TileDecodeError("bad_type", f"idx must be msgpack bin, got {type(idx).__name__}", "idx")
        if len(idx) % 2:
            raise TileDecodeError("bad_length", f"idx must have an even byte length, got {len(idx)}", "idx")
        if len(idx) // 2 != len(val):
            raise TileDecodeError("bad_length", f"idx has {len(idx) // 2} indices but val has {len(val)} bytes", "val")
        indices = np.frombuffer(idx, dtype="<u2")
        if indices.size and int(indices.max()) >= cells:
            raise TileDecodeError(
                "index_out_of_range", f"idx holds {int(indices.max())}, must be < n*n = {cells}", "idx"
            )
        if np.unique(indices).size != indices.size:
            raise TileDecodeError("duplicate_index", "idx repeats a cell", "idx")
        dense = np.zeros(cells, dtype=np.uint8)
        dense[indices] = np.frombuffer(val, dtype=np.uint8)
    return (dense.astype(np.float32) / np.float32(_VALUE_SCALE)).reshape(n, n)
