"""The processes of one run: torch.distributed under torchrun, and nothing home-made.

`zoo fit-category` runs the same way on one process, under ``zoo fit-category --nproc P`` (which
starts torchrun's launcher on this machine) and under ``torchrun --nnodes N --nproc-per-node P -m
sdfzoo.cli fit-category ...`` on several machines. Every process runs every stage:

* a per-mesh stage (:func:`for_each_mesh`) gives each rank the meshes ``stems[rank::world]`` in stem
  order, and each writes that mesh's outputs as a single process would (seeds come from the stem, so
  a mesh's files do not depend on the number of processes); the ranks then exchange what they found
  (results and meshes set aside) with ``all_gather_object``;
* a whole-category stage (training, a merge) is decided by rank 0, built by the ranks that take part,
  and locked by rank 0 (:func:`run_stage_together`).

The work folder must be one folder that every rank sees (a shared file system across machines).
"""

from __future__ import annotations

import datetime
import os
from collections.abc import Callable
from dataclasses import dataclass

import torch

from zoo.validation import as_device

# A rank waits at a barrier while rank 0 alone merges or trains the detector; gloo's default of
# 30 minutes would end a long run there.
BARRIER_TIMEOUT = datetime.timedelta(hours=24)


@dataclass(frozen=True)
class World:
    """This process's place among the run's processes; ``World()`` is a run of one."""

    rank: int = 0
    size: int = 1
    device: torch.device = torch.device("cpu")

    @property
    def main(self) -> bool:
        """Whether this process writes what one process writes (merged files, locks, the package) and prints."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.size > 1

    def share(self, items: list) -> list:
        """This rank's share of ``items``: every ``size``-th, starting at ``rank`` (the order is kept)."""
        return list(items)[self.rank :: self.size]

    def barrier(self) -> None:
        if self.distributed:
            import torch.distributed as dist

            dist.barrier()

    def gather(self, obj) -> list:
        """``obj`` of every rank, in rank order (``[obj]`` on one process)."""
        if not self.distributed:
            return [obj]
        import torch.distributed as dist

        out = [None] * self.size
        dist.all_gather_object(out, obj)
        return out

    def sum(self, tensor: torch.Tensor) -> torch.Tensor:
        """``tensor`` summed over the ranks, in place (unchanged on one process)."""
        if self.distributed:
            import torch.distributed as dist

            dist.all_reduce(tensor)
        return tensor

    def broadcast(self, obj):
        """Rank 0's ``obj`` on every rank."""
        if not self.distributed:
            return obj
        import torch.distributed as dist

        box = [obj]
        dist.broadcast_object_list(box, src=0)
        return box[0]


def launched_size() -> int:
    """The number of processes torchrun started for this run (1 outside torchrun)."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def join_world(device: str | torch.device = "cpu") -> World:
    """This process's :class:`World`; under torchrun, joins the process group (gloo on CPU, nccl on CUDA)
    and picks this process's GPU (``LOCAL_RANK``)."""
    import torch.distributed as dist

    as_device(device)  # an unusable device: a typed error, not torch's AssertionError
    if launched_size() <= 1:
        return World(device=torch.device(device))
    device = torch.device(device)
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo", timeout=BARRIER_TIMEOUT)
    rank = dist.get_rank()
    if device.type == "cuda":
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", rank)))
        torch.cuda.set_device(device)
    return World(rank, dist.get_world_size(), device)


def leave_world(world: World) -> None:
    """End this process's part in the process group (after a last barrier, so no rank leaves early)."""
    if world.distributed:
        import torch.distributed as dist

        dist.barrier()
        dist.destroy_process_group()


def run_stage_together(world: World, stage, build: Callable[[], None], force: bool = False) -> bool:
    """:func:`pipeline.stages.run_stage` for a stage every rank takes part in; -> whether it ran.

    Rank 0 decides whether the stage is up to date and tells the others; every rank calls ``build``
    (which writes outputs on rank 0 only, or per rank); rank 0 writes the lock once all are done.
    """
    from .stages import input_record, is_up_to_date, write_lock

    record = input_record(stage) if world.main else None
    todo = world.broadcast(force or not is_up_to_date(stage, record) if world.main else None)
    if not todo:
        return False
    build()
    world.barrier()
    if world.main:
        write_lock(stage, record)
    world.barrier()
    return True


def average_gradients(parameters, world: World) -> None:
    """Average the gradients of ``parameters`` over the ranks, in one all-reduce (dense parameters: a decoder)."""
    if not world.distributed:
        return
    import torch.distributed as dist

    grads = [p.grad for p in parameters if p.grad is not None]
    if not grads:
        return
    flat = torch.cat([g.reshape(-1) for g in grads])
    dist.all_reduce(flat)
    flat /= world.size
    for g, part in zip(grads, flat.split([g.numel() for g in grads])):
        g.copy_(part.view_as(g))


def average_rows(parameters, rows: torch.Tensor, world: World) -> None:
    """Average over the ranks the gradient rows ``rows`` (B,) of per-shape ``parameters`` (S, ...) that any rank
    touched: a step sends the rows of its batch, not the whole table of every shape's codes.

    Every rank's batch has the same size, so the union of the rows is gathered with one all-gather; the
    rows no rank touched hold a zero gradient on every rank, as a dense all-reduce would leave them.
    """
    if not world.distributed:
        return
    import torch.distributed as dist

    gathered = [torch.empty_like(rows) for _ in range(world.size)]
    dist.all_gather(gathered, rows.contiguous())
    touched = torch.unique(torch.cat(gathered))
    for p in parameters:
        if p.grad is None:
            continue
        part = p.grad[touched]
        dist.all_reduce(part)
        p.grad[touched] = part / world.size


def launch_local(nproc: int, args: list[str]) -> int:
    """Run ``zoo ARGS`` on ``nproc`` processes of this machine under torchrun's launcher; -> its exit code.

    torchrun (``--standalone``: its own rendezvous on localhost) starts the processes, restarts none,
    and gives each one thread unless ``OMP_NUM_THREADS`` says otherwise; libigl's exact distances, which
    thread on their own, get this machine's cores shared out likewise (``IGL_NUM_THREADS``).
    """
    import subprocess
    import sys

    env = {**os.environ}
    env.setdefault("IGL_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // nproc)))
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", str(nproc),
               "-m", "sdfzoo.cli", *args]
    return subprocess.run(command, env=env, check=False).returncode
