"""Output: HDF5 snapshots (one file per output time), an XDMF sidecar for ParaView,
and ``summary.json``. Files are written to a temporary name and renamed (atomic)."""
from __future__ import annotations

import json
import os
from pathlib import Path

import h5py
import numpy as np
import torch

from .state import ParticleState

# dataset name -> (state field, XDMF attribute type)
DATASETS = {
    "position": ("x", None),
    "velocity": ("v", "Vector"),
    "density": ("rho", "Scalar"),
    "pressure": ("p", "Scalar"),
    "mass": ("m", "Scalar"),
    "temperature": ("T", "Scalar"),
    "peak_temperature": ("T_peak", "Scalar"),
    "phase": ("phase", "Scalar"),
    "id": ("id", "Scalar"),
    "body": ("body", "Scalar"),
}


def _as3(a: np.ndarray) -> np.ndarray:
    """Pad (N, 2) vectors to (N, 3) so that ParaView reads 2-D runs as XYZ / 3-vectors."""
    if a.ndim == 2 and a.shape[1] == 2:
        return np.concatenate([a, np.zeros((a.shape[0], 1), dtype=a.dtype)], axis=1)
    return a


def snapshot_arrays(state: ParticleState) -> dict[str, np.ndarray]:
    """Fields as numpy arrays ordered by particle id."""
    order = torch.argsort(state.id)
    out = {}
    for name, (fld, _) in DATASETS.items():
        a = getattr(state, fld)[order].detach().cpu().numpy()
        if fld == "phase":
            a = a.astype(np.int32)
        out[name] = _as3(a)
    return out


def write_snapshot(path: Path, state: ParticleState, t: float, step: int):
    arrays = snapshot_arrays(state)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with h5py.File(tmp, "w") as f:
        f.attrs["time"] = t
        f.attrs["step"] = step
        f.attrs["dim"] = state.dim
        for name, a in arrays.items():
            f.create_dataset(name, data=a)
    os.replace(tmp, path)


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


def write_xdmf(path: Path, snapshots: list[tuple], float_dtype):
    """Temporal collection of Polyvertex grids, one per snapshot (t, file, particle count):
    the count may change between snapshots (a fed wire adds particles)."""
    fdt = np.dtype(float_dtype)
    grids = []
    for t, fname, n in snapshots:
        attrs = []
        for name, (fld, atype) in DATASETS.items():
            if atype is None:
                continue
            if fld == "v":
                shape, dt = (n, 3), fdt
            elif fld == "phase":
                shape, dt = (n,), np.dtype(np.int32)
            elif fld in ("id", "body"):
                shape, dt = (n,), np.dtype(np.int64)
            else:
                shape, dt = (n,), fdt
            attrs.append(f'    <Attribute Name="{name}" AttributeType="{atype}" Center="Node">'
                         f'{_dataitem(fname, name, shape, dt)}</Attribute>')
        grids.append(
            f'   <Grid Name="particles" GridType="Uniform">\n    <Time Value="{t:.10g}"/>\n'
            f'    <Topology TopologyType="Polyvertex" NumberOfElements="{n}" NodesPerElement="1"/>\n'
            f'    <Geometry GeometryType="XYZ">{_dataitem(fname, "position", (n, 3), fdt)}</Geometry>\n'
            + "\n".join(attrs) + "\n   </Grid>")
    text = ('<?xml version="1.0" ?>\n<Xdmf Version="3.0">\n <Domain>\n'
            '  <Grid Name="run" GridType="Collection" CollectionType="Temporal">\n'
            + "\n".join(grids) + "\n  </Grid>\n </Domain>\n</Xdmf>\n")
    tmp = path.with_suffix(".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_json(path: Path, data: dict):
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")
    os.replace(tmp, path)
