"""Ground truth: batched explicit visco-hyperelastic FEM in Warp (imported as warpgnn.fem_ref)."""

from .loads import LoadCase, LoadSampler, make_load_case
from .material import OgdenProny
from .solver import BatchedExplicitSolver, SimulationResult, SolverConfig, elastic_nodal_stress, stable_time_step

__all__ = ["BatchedExplicitSolver", "LoadCase", "LoadSampler", "OgdenProny", "SimulationResult",
           "SolverConfig", "elastic_nodal_stress", "make_load_case", "stable_time_step"]
