"""The physics: the weakly compressible fluid, conduction and its operator, the beams, the
free-surface stage, surface forces, wetting, and the composable terms (``terms/``). Imports only
:mod:`torchsph.core` and itself; never the step, a decomposition or MPI."""
