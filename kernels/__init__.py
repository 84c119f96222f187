"""Hand-written Warp kernels for the network (fused message passing, GENERIC tail).

Imported as ``warpgnn.kernels``; filled in by the GNN issue.
"""
