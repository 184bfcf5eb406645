"""Where a training run runs: its device, its mixed precision, and its place among torchrun's processes.

One process (``python -m mld_core train ...``) or several (``torchrun --nproc_per_node N -m mld_core train ...``,
``--nnodes`` for several machines): every trainer asks :func:`runtime` for a :class:`Runtime` and follows one rule
that makes the number of processes invisible in what it learns:

- every step's batch is drawn whole, by every process alike, from a generator keyed by (seed, step) (:func:`step_rng`),
  and process r takes rows r, r + N, r + 2N, ... of it (DistributedSampler's split of one shared draw, weighted or
  not); its loss is weighted by its share of the rows (:meth:`Runtime.share`), and DDP averages the gradients, so the
  update is the one a single process makes on the whole batch. Batch sizes in a stage's config are totals.
- rank 0 alone writes (checkpoints, logs, the progress bar); the others read what it wrote after a barrier (several
  machines need the run folder on a shared file system).
- everything saved is CPU tensors, so a run resumes on another device or another number of processes.

CUDA trains in mixed precision by default (bfloat16 autocast where the GPU has it, else float16 with a gradient
scaler); the CPU in float32, or bfloat16 autocast with ``--bf16``.
"""

from __future__ import annotations

import datetime
import os
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np
import torch

from mld_core import inputs


@dataclass
class Runtime:
    """This process's device, precision and place among the run's processes."""

    device: torch.device
    world: inputs.World = inputs.World()
    amp_dtype: torch.dtype | None = None  # the autocast dtype; None: float32
    scaler: object | None = None  # torch.amp.GradScaler for float16

    @property
    def rank(self) -> int:
        return self.world.rank

    @property
    def size(self) -> int:
        return self.world.size

    @property
    def is_main(self) -> bool:
        return self.world.rank == 0

    @property
    def precision(self) -> str:
        return {torch.bfloat16: "bf16", torch.float16: "fp16"}.get(self.amp_dtype, "fp32")

    def describe(self, total_batch: int, what: str = "clips") -> dict:
        """What the run's config records about where it ran (train_config.json)."""
        return {"device": self.device.type, "precision": self.precision, "world_size": self.size,
                "batch_total": total_batch, "batch_per_process": -(-total_batch // self.size), "batch_of": what}

    # -- the batch ----------------------------------------------------------------------------------------------
    def rows(self, total: int) -> np.ndarray:
        """This process's rows of a batch of ``total``: r, r + N, ..."""
        return np.arange(self.rank, total, self.size)

    def share(self, total: int) -> float:
        """The weight of this process's mean loss, so that DDP's average of the processes' gradients is the
        gradient of the whole batch's mean: N x (its rows / total)."""
        return self.size * len(range(self.rank, total, self.size)) / total

    def to_device(self, tensor: torch.Tensor) -> torch.Tensor:
        """A CPU tensor on the device (pinned first, so the copy overlaps the GPU's work)."""
        if self.device.type == "cuda":
            return tensor.pin_memory().to(self.device, non_blocking=True)
        return tensor.to(self.device)

    # -- forward and backward -------------------------------------------------------------------------------------
    def autocast(self):
        if self.amp_dtype is None:
            return nullcontext()
        return torch.autocast(self.device.type, dtype=self.amp_dtype)

    def wrap(self, module: torch.nn.Module, unused: bool = False) -> torch.nn.Module:
        """``module`` (whose forward returns the loss) in DistributedDataParallel when there are several processes;
        ``unused``: some trained parameters take no part in the loss (a Draft student's null condition)."""
        if self.size == 1:
            return module
        import inspect

        from torch.nn.parallel import DistributedDataParallel

        ids = [self.device.index] if self.device.type == "cuda" else None
        # no stage has buffers that training changes: they are synced once, not at every step
        sync = ({"forward_sync_buffers": False} if "forward_sync_buffers" in
                inspect.signature(DistributedDataParallel.__init__).parameters else {"broadcast_buffers": False})
        return DistributedDataParallel(module, device_ids=ids, find_unused_parameters=unused, **sync)

    def step(self, loss: torch.Tensor, optimizer: torch.optim.Optimizer, params: list, clip: float = 1.0) -> None:
        """Backward (gradients averaged over the processes by DDP), clip, and one optimiser step (float16: scaled)."""
        optimizer.zero_grad(set_to_none=True)
        if self.scaler is None:
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, clip)
            optimizer.step()
            return
        self.scaler.scale(loss).backward()
        self.scaler.unscale_(optimizer)
        torch.nn.utils.clip_grad_norm_(params, clip)
        self.scaler.step(optimizer)
        self.scaler.update()

    # -- the processes agree ------------------------------------------------------------------------------------
    def barrier(self) -> None:
        if self.size > 1:
            torch.distributed.barrier()

    def on_main(self, work) -> None:
        """Run ``work`` on rank 0 alone; the others wait and raise its error (a ValueError) if it failed."""
        if self.size == 1:
            work()
            return
        message = [""]
        if self.is_main:
            try:
                work()
            except (OSError, ValueError) as exc:  # FileExistsError, FileNotFoundError, InputError ...
                message[0] = f"{type(exc).__name__}: {exc}"
                torch.distributed.broadcast_object_list(message, src=0)
                raise
        torch.distributed.broadcast_object_list(message, src=0)
        if message[0] and not self.is_main:
            raise ValueError(message[0].split(": ", 1)[1])

    def decide(self, flag: bool) -> bool:
        """Rank 0's ``flag`` in every process (a time budget spent by its clock)."""
        if self.size == 1:
            return bool(flag)
        value = torch.tensor([float(flag)], device=self.device)
        torch.distributed.broadcast(value, src=0)
        return bool(value.item() > 0.5)

    def budget(self, budget):
        """``budget`` (common.Budget) as every process sees it: rank 0's clock decides when a time budget is spent
        and how far the learning-rate schedule is, so the processes stop together and keep one learning rate."""
        if self.size == 1 or budget.max_minutes is None:
            return budget
        return _SharedBudget(budget, self.device)


class _SharedBudget:
    """A Budget whose progress and end rank 0 tells the others, once per step."""

    def __init__(self, budget, device: torch.device):
        self.inner, self.device = budget, device
        self.max_steps, self.max_minutes = budget.max_steps, budget.max_minutes
        self._step, self._state = None, (0.0, False)

    def _agree(self, step: int) -> tuple[float, bool]:
        if step != self._step:
            state = torch.tensor([self.inner.progress(step), float(self.inner.done(step))], dtype=torch.float64,
                                 device=self.device)
            torch.distributed.broadcast(state, src=0)
            self._step, self._state = step, (float(state[0]), bool(state[1] > 0.5))
        return self._state

    def done(self, step: int) -> bool:
        return self._agree(step)[1]

    def progress(self, step: int) -> float:
        return self._agree(step)[0]

    @property
    def minutes(self) -> float:
        return self.inner.minutes


def step_rng(seed: int, step: int) -> tuple[np.random.Generator, torch.Generator]:
    """The generators of one step's batch (rows, crops, noise, timesteps): the same in every process and in a
    resumed run, whatever ran before."""
    rng = np.random.default_rng([int(seed), int(step)])
    return rng, torch.Generator().manual_seed(int(rng.integers(2**62)))


_STARTED: Runtime | None = None


def runtime(device: str = "cpu", bf16: bool = False, fp32: bool = False, batch: tuple[int, str] | None = None
            ) -> Runtime:
    """This process's Runtime (once per process): ``device`` checked (auto resolved), torchrun's environment read,
    ``batch`` (its total size and its name) checked to give every process a row and, with several processes, the
    process group started (gloo on the CPU, NCCL on CUDA). Precision: CUDA autocasts to bfloat16 (float16 with a
    gradient scaler on GPUs without it) unless ``fp32``; elsewhere bfloat16 with ``bf16``."""
    global _STARTED
    name = inputs.check_device(device)
    world = inputs.check_world(os.environ, name)
    if batch is not None and batch[0] < world.size:
        raise inputs.InputError(f"{batch[1]} is {batch[0]}, fewer than the {world.size} processes: each needs a "
                                f"row; raise it to at least {world.size} (it is the total over all processes)")
    if _STARTED is not None and _STARTED.world == world and _STARTED.device.type == name:
        return _with_precision(_STARTED, bf16, fp32)
    torch_device = torch.device(f"cuda:{world.local_rank}" if name == "cuda" else name)
    if name == "cuda":
        torch.cuda.set_device(torch_device)
    if world.size > 1 and not torch.distributed.is_initialized():
        torch.distributed.init_process_group("nccl" if name == "cuda" else "gloo", rank=world.rank,
                                             world_size=world.size, timeout=datetime.timedelta(minutes=30))
    _STARTED = Runtime(torch_device, world)
    return _with_precision(_STARTED, bf16, fp32)


def _with_precision(rt: Runtime, bf16: bool, fp32: bool) -> Runtime:
    dtype, scaler = None, None
    if rt.device.type == "cuda" and not fp32:
        if bf16 or torch.cuda.is_bf16_supported():
            dtype = torch.bfloat16
        else:
            dtype, scaler = torch.float16, torch.amp.GradScaler("cuda")
    elif bf16:
        dtype = torch.bfloat16
    return Runtime(rt.device, rt.world, dtype, scaler)


def finish() -> None:
    """Wait for every process, then end the process group (when there is one)."""
    global _STARTED
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.barrier()
        torch.distributed.destroy_process_group()
    _STARTED = None


def is_main_process() -> bool:
    """Whether this process is rank 0 (or the only one), from torchrun's environment (before any group starts)."""
    return str(os.environ.get("RANK", "0")).strip() in ("", "0")


def unwrapped(module: torch.nn.Module) -> torch.nn.Module:
    """The module inside a DDP wrapper (or the module itself)."""
    return getattr(module, "module", module)
