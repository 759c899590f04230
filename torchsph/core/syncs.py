"""Counting host synchronisations on any device (CPU included).

On a GPU every operation whose result the host must read (a Python number, a
data-dependent shape, a copy from or to host memory) stops the host until the device has
caught up; on a CPU nothing waits, so the count is the only way to see them. A
:class:`SyncCounter` is a ``TorchFunctionMode`` that counts, by name, the calls that would
block on a CUDA device: reads to Python (``item``, ``tolist``, ``bool``/``float``/``int``
of a tensor), data-dependent shapes (``nonzero``, ``unique``, ``masked_select``, boolean
indexing, ``repeat_interleave`` without an output size, ``bincount``) and host-device copies
(``torch.tensor``/``as_tensor`` of Python data, ``cpu``, ``numpy``). Calls made inside torch
(C++) are not seen.

    with SyncCounter() as c:
        run_steps(sim, steps=50)
    print(c.total, c.by_name)
"""
from __future__ import annotations

from collections import Counter

import torch
from torch.overrides import TorchFunctionMode

_READS = {"item", "tolist", "__bool__", "__float__", "__int__", "__index__", "cpu", "numpy"}
_SHAPES = {"nonzero", "argwhere", "unique", "unique_consecutive", "masked_select", "bincount"}
_COPIES = {"tensor", "as_tensor"}


def _bool_index(idx) -> bool:
    items = idx if isinstance(idx, tuple) else (idx,)
    return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in items)


def _is_sync(name: str, args, kwargs) -> bool:
    if name in _READS or name in _SHAPES:
        return True
    if name in _COPIES:  # from Python data or another device
        data = args[0] if args else kwargs.get("data")
        return not isinstance(data, torch.Tensor) or (kwargs.get("device") is not None)
    if name in ("__getitem__", "__setitem__", "index_put_", "index_put"):
        return len(args) > 1 and _bool_index(args[1])
    if name == "repeat_interleave":
        return kwargs.get("output_size") is None and len(args) > 1 and isinstance(args[1], torch.Tensor)
    return False


class SyncCounter(TorchFunctionMode):
    """Counts the torch calls that would synchronise a CUDA device with its host."""

    def __init__(self):
        super().__init__()
        self.by_name: Counter = Counter()
        self._depth = 0

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", str(func))
        if self._depth == 0 and _is_sync(name, args, kwargs):
            self.by_name[name] += 1
        self._depth += 1
        try:
            return func(*args, **kwargs)
        finally:
            self._depth -= 1

    @property
    def total(self) -> int:
        return sum(self.by_name.values())
