"""Child process of ``test_shutdown_leaves_no_communication_thread``, run by ``torchrun --nproc_per_node=2``:
joins the process group as ``train.py`` does (:func:`nsplat.run.distributed.init_from_env`), renders a tiny scene
with the op (whose first call loads ``torch._dynamo``), sums the gradients over the ranks, leaves the group
(:func:`nsplat.run.distributed.shutdown`) and prints, as JSON, the communication threads still alive.

``--no-early-import`` skips the import that :func:`init_from_env` does before joining (the cause of the abort
at exit that the test guards against), to show that the check sees a group kept alive. That run then leaves with
``os._exit`` once it has printed: its leaked gloo threads may abort a normal interpreter exit (the very bug), which
would hide the threads it reports; the default run exits normally, so its exit status is checked too."""
from __future__ import annotations

import json
import os
import sys

import torch

from nsplat.ops import splat
from nsplat.run import distributed


def main(argv: list[str]) -> None:
    if "--no-early-import" in argv:
        distributed._import_group_capturing_modules = lambda: None
    distributed.init_from_env(torch.device("cpu"), timeout_s=60)
    g = torch.Generator().manual_seed(distributed.rank())
    N = 32
    means = ((torch.rand(N, 3, generator=g) - 0.5) * 0.8).requires_grad_()
    normals = torch.tensor([[0.0, 0.0, -1.0]]).repeat(N, 1)
    scales = torch.full((N, 2), 0.1)
    opacities = torch.full((N,), 0.8)
    features = torch.rand(N, 3, generator=g)
    viewmat = torch.eye(4).unsqueeze(0)
    viewmat[0, 2, 3] = 2.5
    K = torch.tensor([[[20.0, 0.0, 8.0], [0.0, 20.0, 8.0], [0.0, 0.0, 1.0]]])
    out = splat(means, normals, scales, opacities, features, viewmat, K, 16, 16, samples=4, seed=1)
    out.image.sum().backward()
    distributed.all_reduce_grads([means])
    distributed.shutdown()
    print(json.dumps({"rank_threads": distributed.communication_threads()}), flush=True)
    if "--no-early-import" in argv:
        os._exit(0)


if __name__ == "__main__":
    main(sys.argv[1:])
