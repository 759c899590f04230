"""Output: HDF5 snapshots (one file per output time), an XDMF sidecar for ParaView,
and ``summary.json``. Files are written to a temporary name and renamed (atomic)."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import h5py
import numpy as np
import torch

from torchsph.core.state import FIELDS, ParticleState


class OutputError(RuntimeError):
    """An output file (snapshot, checkpoint, sidecar) could not be written: the message names
    the file and the cause in one line. The file it was to replace is left as it was."""


def _cause(e: BaseException) -> str:
    """The operating system's reason behind ``e`` where there is one (a full disk reached
    through torch's or h5py's own errors), else ``e``'s first line."""
    seen = e
    while seen is not None:
        if isinstance(seen, OSError) and seen.strerror:
            return seen.strerror
        seen = seen.__cause__ or seen.__context__
    return f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"


def written(path: Path, write, tmp: Path | None = None):
    """``write(tmp)``, then ``tmp`` renamed over ``path`` (atomic). Where writing fails (a full
    disk, a lost mount) the temporary file is removed and :class:`OutputError` is raised:
    ``path`` is left as it was."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp") if tmp is None else tmp
    try:
        write(tmp)
        os.replace(tmp, path)
    except Exception as e:  # noqa: BLE001 - any failure of the write: said in one line
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        raise OutputError(f"could not write {path} ({_cause(e)})") from e


def free_bytes(path: Path) -> float | None:
    """Bytes free on the disk of ``path`` (or of its nearest existing parent); None if unknown."""
    p = Path(path).resolve()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        return float(shutil.disk_usage(p).free)
    except OSError:
        return None


def _as3(a: np.ndarray) -> np.ndarray:
    """Pad (N, 2) vectors to (N, 3) so that ParaView reads 2-D runs as XYZ / 3-vectors."""
    if a.ndim == 2 and a.shape[1] == 2:
        return np.concatenate([a, np.zeros((a.shape[0], 1), dtype=a.dtype)], axis=1)
    return a


def _plain(a: np.ndarray) -> np.ndarray:
    """What a snapshot stores: bool and int8 as int32 (ParaView reads them), vectors as XYZ."""
    if a.dtype == np.bool_ or a.dtype == np.int8:
        a = a.astype(np.int32)
    return _as3(a)


def snapshot_arrays(state: ParticleState, extra: dict | None = None) -> dict[str, np.ndarray]:
    """The state's fields under their dataset names (:data:`torchsph.core.state.FIELDS`), and
    ``extra`` (dataset name -> per-particle array in the state's row order: ``[run] fields``),
    as numpy arrays ordered by particle id."""
    order = torch.argsort(state.id)
    out = {f.dataset: _plain(getattr(state, k)[order].detach().cpu().numpy()) for k, f in FIELDS.items()}
    for name, a in (extra or {}).items():
        a = a[order.to(a.device)].detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)[order.cpu().numpy()]
        out[name] = _plain(a.reshape(a.shape[0], -1) if a.ndim > 2 else a)
    return out


def layout(arrays: dict[str, np.ndarray]) -> dict[str, tuple[tuple, str]]:
    """Dataset name -> (shape after the particle axis, numpy dtype name): what the XDMF sidecar
    describes (:func:`write_xdmf`)."""
    return {k: (tuple(a.shape[1:]), a.dtype.str) for k, a in arrays.items()}


def write_snapshot(path: Path, state: ParticleState, t: float, step: int, extra: dict | None = None) -> dict:
    """One snapshot file (atomic); returns its :func:`layout`."""
    arrays = snapshot_arrays(state, extra)

    def write(tmp):
        with h5py.File(tmp, "w") as f:
            f.attrs["time"] = t
            f.attrs["step"] = step
            f.attrs["dim"] = state.dim
            for name, a in arrays.items():
                f.create_dataset(name, data=a)
    written(path, write)
    return layout(arrays)


def read_snapshot(path) -> dict:
    with h5py.File(path, "r") as f:
        out = {k: f[k][()] for k in f.keys()}
        out.update({k: f.attrs[k] for k in f.attrs})
    return out


def _dataitem(fname: str, name: str, a_shape, dtype) -> str:
    kind = "Int" if np.issubdtype(dtype, np.integer) else "Float"
    dims = " ".join(str(s) for s in a_shape)
    return (f'<DataItem Dimensions="{dims}" NumberType="{kind}" Precision="{np.dtype(dtype).itemsize}" '
            f'Format="HDF">{fname}:/{name}</DataItem>')


def write_xdmf(path: Path, snapshots: list[tuple], float_dtype, datasets: dict):
    """Temporal collection of Polyvertex grids, one per snapshot (t, file, particle count[,
    the names of its ``[run] fields``]): the count may change between snapshots (a fed wire
    adds particles), and so may the fields (a restart may name others). ``datasets``: the
    snapshots' :func:`layout`: (N,) arrays are scalars, (N, 3) vectors, others matrices."""
    fdt = np.dtype(float_dtype)
    grids = []
    state = {f.dataset for f in FIELDS.values()}
    for t, fname, n, *more in snapshots:
        attrs = []
        extra = set(more[0]) if more else set()
        for name, (tail, dts) in datasets.items():
            if name == "position" or (name not in state and name not in extra):
                continue
            dt = np.dtype(dts)
            atype = "Vector" if tail == (3,) else "Scalar" if tail == () else "Matrix"
            attrs.append(f'    <Attribute Name="{name}" AttributeType="{atype}" Center="Node">'
                         f'{_dataitem(fname, name, (n, *tail), dt)}</Attribute>')
        grids.append(
            f'   <Grid Name="particles" GridType="Uniform">\n    <Time Value="{t:.10g}"/>\n'
            f'    <Topology TopologyType="Polyvertex" NumberOfElements="{n}" NodesPerElement="1"/>\n'
            f'    <Geometry GeometryType="XYZ">{_dataitem(fname, "position", (n, 3), fdt)}</Geometry>\n'
            + "\n".join(attrs) + "\n   </Grid>")
    text = ('<?xml version="1.0" ?>\n<Xdmf Version="3.0">\n <Domain>\n'
            '  <Grid Name="run" GridType="Collection" CollectionType="Temporal">\n'
            + "\n".join(grids) + "\n  </Grid>\n </Domain>\n</Xdmf>\n")
    written(path, lambda tmp: tmp.write_text(text))


def write_json(path: Path, data: dict):
    text = json.dumps(data, indent=2, sort_keys=False) + "\n"
    written(path, lambda tmp: tmp.write_text(text))
