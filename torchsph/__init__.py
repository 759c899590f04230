"""torchsph: weakly compressible SPH in PyTorch for melt-pool simulation."""
from torchsph.core.kernels import CubicSpline, WendlandC2, make_kernel
from torchsph.core.neighbors import Domain, brute_force_pairs, build_pairs, build_table
from torchsph.core.state import ParticleState, Phase
from torchsph.core.verlet import VerletList
from torchsph.io.config import CaseError, load_case

__version__ = "0.1.0"
__all__ = ["CaseError", "load_case", "CubicSpline", "WendlandC2", "make_kernel", "Domain",
           "VerletList", "brute_force_pairs", "build_pairs", "build_table", "ParticleState", "Phase"]
