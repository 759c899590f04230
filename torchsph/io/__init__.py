"""Cases in, results out: the case schema and its validation, checkpoints, HDF5 snapshots with
their XDMF sidecar."""
