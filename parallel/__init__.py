"""MPI domain decomposition (slabs along the travel axis): ``slab.py`` (ghost halos,
migration, load balance), ``run.py`` (the run loop over ranks), ``driver.py`` (a test driver).

The single-process solver in ``torchsph`` never imports MPI.
"""
