"""The lowest layer: the particle state and the array declarations, kernels, the domain and the
neighbour search, lattices, the case schema's building blocks, exact solutions. Imports nothing
above it."""
