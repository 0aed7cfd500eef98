"""A rank that counts the references to its gloo group before and after destroy_process_group.

Kept free of heliotwin imports: a spawned rank imports this module only, so the control rank (torch's own
``init_process_group``) starts without the ``torch._dynamo`` import that importing heliotwin.distributed does.
"""
import sys

import torch
import torch.distributed as dist


def release_worker(rank, world, folder, init, tag):
    init("gloo", init_method=f"file://{folder}/store-release", rank=rank, world_size=world)
    group = dist.distributed_c10d._get_default_group()
    before = sys.getrefcount(group)
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])  # the first optimiser imports torch._dynamo
    dist.destroy_process_group()
    with open(f"{folder}/refs-{tag}.txt", "w") as f:
        f.write(f"{before} {sys.getrefcount(group)}")
