"""The time step: the simulation and its integrator, the rates summed over the physics, the
time-step limits and the blow-up diagnosis, the per-particle array registry, the active set,
phase changes and the bookkeeping, and the decomposition's hooks (``comm``)."""
