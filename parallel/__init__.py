"""MPI domain decomposition (slabs along the travel axis); not yet implemented.

The single-process solver in ``torchsph`` never imports MPI.
"""
