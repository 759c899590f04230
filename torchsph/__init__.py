"""torchsph: weakly compressible SPH in PyTorch for melt-pool simulation."""
from .config import CaseError, load_case
from .kernels import CubicSpline, WendlandC2, make_kernel
from .neighbors import Domain, VerletList, brute_force_pairs, build_pairs, build_table
from .state import ParticleState, Phase

__version__ = "0.1.0"
__all__ = ["CaseError", "load_case", "CubicSpline", "WendlandC2", "make_kernel", "Domain",
           "VerletList", "brute_force_pairs", "build_pairs", "build_table", "ParticleState", "Phase"]
