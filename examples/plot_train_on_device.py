"""
Features computed on the device inside the training step
========================================================

A training loop that augments its meshes every step (a random rotation and a jitter of the
vertices along their normals) has to recompute the features every step: here
:class:`stochlap_torch.MultiscaleFeatures` does so on the model's device (CUDA when there is
one, else the CPU) and in its dtype (float32), from a
:func:`stochlap_torch.robust_structure` built once per mesh and moved there with
``.to(device)``. The structure holds the pyramid and the operators of the clean mesh; the call
diffuses the jittered positions with them, so a step costs the diffusion alone, not the
decimation and the eigen solve.

The task, small enough to run in seconds on the bundled ``spot`` cow: a per-vertex network
learns the saliency of the clean mesh (:func:`stochlap_torch.saliency`, the robust variant)
from the features of jittered copies, and is then scored on a copy it never saw, against the
saliency computed directly on that copy.
"""

# %%
# The mesh, its structure on the device, and the target: the clean mesh's saliency.
import time

import torch
from scipy.stats import spearmanr

import stochlap_torch as sl

torch.manual_seed(0)
device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
mesh = sl.load_mesh(sl.bundled_mesh_path(), dtype=torch.float32)
vertices, faces = mesh.vertices.to(device), mesh.faces.to(device)
structure = sl.robust_structure(vertices, faces).to(device)  # once per mesh
target = sl.saliency(vertices, faces, structure=structure)  # (V,), float32 on the device
target = (target - target.mean()) / target.std()
normals = sl.vertex_normals(vertices, faces)
edges = vertices[faces] - vertices[faces.roll(1, dims=1)]
jitter = 0.3 * float(edges.norm(dim=-1).mean())  # a third of the mean edge length


def augmented() -> torch.Tensor:
    """``(V, 3)`` a rotated copy of the mesh, every vertex moved along its normal."""
    rotation = torch.linalg.qr(torch.randn(3, 3, device=device)).Q
    moved = vertices + jitter * torch.randn(len(vertices), 1, device=device) * normals
    return moved @ rotation.T


# %%
# The training step computes the features of a fresh copy on the device.
features = sl.MultiscaleFeatures().to(device)
net = torch.nn.Sequential(
    torch.nn.Linear(features.num_channels, 64),
    torch.nn.ReLU(),
    torch.nn.Linear(64, 64),
    torch.nn.ReLU(),
    torch.nn.Linear(64, 1),
).to(device)
optimiser = torch.optim.Adam(net.parameters(), lr=3e-3)
start = time.perf_counter()
for step in range(150):
    x = features(augmented(), faces, structure=structure)  # (V, C) float32, on the device
    loss = torch.nn.functional.mse_loss(net(x).squeeze(1), target)
    optimiser.zero_grad()
    loss.backward()
    optimiser.step()
    if step % 50 == 0:
        print(f"step {step:3d}  loss {loss.item():.3f}")
elapsed = time.perf_counter() - start
print(f"150 steps in {elapsed:.1f} s on {device} ({1e3 * elapsed / 150:.0f} ms a step)")

# %%
# Scored on an unseen copy: the network's output against the saliency computed on the copy
# itself, both compared with the clean mesh's (Spearman rank correlation).
with torch.no_grad():
    copy = augmented()
    predicted = net(features(copy, faces, structure=structure)).squeeze(1)
    direct = sl.saliency(copy, faces, structure=structure)
rho_net = spearmanr(predicted.cpu(), target.cpu())[0]
rho_direct = spearmanr(direct.cpu(), target.cpu())[0]
print(f"rank agreement with the clean saliency: network {rho_net:.3f}, direct {rho_direct:.3f}")
