"""Hand-written Warp kernels for the network: the forward step of a TIGNN (vanilla or hybrid) with
fused message passing and a one-launch GENERIC tail. Imported as ``warpgnn.kernels``.

    from warpgnn.kernels import Network, WarpModel
    net = Network(model, topology, device="cuda:0")
    warp = WarpModel(model)      # the same behind the TIGNN's interface (--backend warp)

Modules: spec (what kernels are compiled for, the covered configurations), weights (a checkpoint
packed once), graph (a topology's CSR layout), tiles (tile building blocks), features,
message_passing (encoders and passes), register_tiles (64-row tiles in a warpgroup's registers:
the shared C++ steps), register_edges (the edge pass and mesh-edge encoder on them), register_nodes
(the node pass on them), decoders, generic_tail, integrate (Euler and boundary conditions), network
(buffers, launches, CUDA graph capture), pdl (overlapped launches in the captured graphs), backend
(WarpModel: the Network behind the model's narrow interface, one per topology, whole rollouts as one
captured graph).
"""

from .backend import WarpModel
from .network import Network
from .spec import check_config

__all__ = ["Network", "WarpModel", "check_config"]
