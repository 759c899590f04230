"""The scenes a case can name: the registry of builders and the deposition scene (wire feeder,
escape box, bead measures)."""
