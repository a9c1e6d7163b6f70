"""Tensors on the wire: raw little-endian C-order bytes with a numpy dtype name and a shape."""

from __future__ import annotations

import math

import numpy as np

from quicknav_client.proto.quicknav.v1 import rollout_pb2 as pb

# Only plain numeric dtypes travel; anything else is refused by name.
WIRE_DTYPES = frozenset(
    ["float32", "float64", "float16", "int8", "int16", "int32", "int64", "uint8", "uint16",
     "uint32", "uint64", "bool"]
)  # fmt: skip


class TensorError(ValueError):
    """A Tensor message that cannot be decoded (unknown dtype, size not matching the shape)."""


def encode(array, dtype: str | None = None) -> pb.Tensor:
    """A numpy array (or anything array-like) as a Tensor message."""
    a = np.asarray(array, dtype=dtype)
    name = a.dtype.name
    if name not in WIRE_DTYPES:
        raise TensorError(f"dtype {name!r} cannot travel; allowed: {sorted(WIRE_DTYPES)}")
    le = a.astype(a.dtype.newbyteorder("<"), copy=False)
    return pb.Tensor(dtype=name, shape=a.shape, data=np.ascontiguousarray(le).tobytes())


def decode(tensor: pb.Tensor, field: str = "tensor") -> np.ndarray:
    """The numpy array a Tensor message holds (read-only view of its bytes)."""
    if tensor.dtype not in WIRE_DTYPES:
        raise TensorError(
            f"{field}.dtype={tensor.dtype!r} is not supported; allowed: {sorted(WIRE_DTYPES)}"
        )
    dt = np.dtype(tensor.dtype).newbyteorder("<")
    shape = tuple(int(s) for s in tensor.shape)
    if any(s < 0 for s in shape):
        raise TensorError(f"{field}.shape={list(shape)} has a negative dimension")
    count = math.prod(shape)  # Python integers: no overflow for absurd shapes
    if count * dt.itemsize != len(tensor.data):
        raise TensorError(
            f"{field}: {len(tensor.data)} bytes do not hold a {tensor.dtype} array of shape"
            f" {list(shape)} ({count * dt.itemsize} bytes expected)"
        )
    return np.frombuffer(tensor.data, dtype=dt).reshape(shape)
