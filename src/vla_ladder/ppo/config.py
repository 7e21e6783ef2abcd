"""`Args` of the PPO expert trainer: every field is a command-line flag (`vla-ladder train-expert --help`).

Defaults are the paper's appendix table; the ones it does not list are ManiSkill's PPO baseline values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Annotated

import tyro

from vla_ladder.checks import check_output_dir, check_seed
from vla_ladder.conditions import Condition, ConditionGrid
from vla_ladder.contract import EPISODE_STEPS
from vla_ladder.machine import cores
from vla_ladder.task.physx_gpu import check_sim_backend

# Training episodes take seeds in [TRAIN_SEED_MIN, 2**32) (numpy's seed limit); evaluation seeds stay
# below, so `vla-ladder eval --first-seed S` with any S + episodes <= TRAIN_SEED_MIN is held out.
TRAIN_SEED_MIN = 2**30


RUN_FILES = ("config.json", "state.json", "checkpoints", "evals.json", "tb")
"""what a run writes in --out (a run killed before its first checkpoint holds some of them and starts again)"""


@dataclass
class Args:
    """Train the PPO privileged-state expert (CleanRL-style PPO on GraspObject-v1)."""

    out: Path
    """directory of the run: config.json, state.json, checkpoints/, evals.json, tb/ (TensorBoard)"""
    resume: bool = False
    """continue the run in --out from its last checkpoint (same step count and optimizer state); flags given
    with --resume override the run's saved ones"""
    train_seed: int = 1
    """seed of the experiment (network init, action sampling, training episode seeds)"""
    cuda: bool = True
    """run the networks on CUDA when available (with physx_cuda they always do, --no-cuda or not)"""
    progress: bool = True
    """show a progress bar"""
    torch_threads: int = 1
    """CPU threads for the networks when they run on the CPU (their batches are small and the simulator
    needs the cores: 2 threads on a busy 2-core machine made each forward pass ~50x slower)"""

    # Environment
    sim_backend: str = "physx_cuda"
    """physx_cuda (GPU-parallel envs; the default, the paper's setting) or physx_cpu (one env in-process, several
    through AsyncVectorEnv, one process each). Without a CUDA GPU the default is refused, never silently swapped:
    pass --sim-backend physx_cpu with a --num-envs and --total-timesteps a CPU can run"""
    num_envs: int = 1024
    """parallel environments (physx_cpu: one process each, at most one per core)"""
    max_episode_steps: int = EPISODE_STEPS
    """episode length in control steps (20 Hz)"""
    grid: Annotated[ConditionGrid, tyro.conf.arg(name="")] = field(
        default_factory=lambda: ConditionGrid(splits=("canonical",), num_objects=(1, 3, 5)))
    """conditions trained on, as a mixture (env slots cycle through every condition)"""

    # Algorithm (the paper's appendix table)
    total_timesteps: int = 30_000_000
    """total env steps of training"""
    learning_rate: float = 1e-4
    """AdamW learning rate"""
    weight_decay: float = 1e-5
    """AdamW weight decay"""
    num_steps: int = 50
    """steps per env in each rollout"""
    num_minibatches: int = 2
    """minibatches per update epoch"""
    update_epochs: int = 4
    """passes over each rollout"""
    gamma: float = 0.8
    """discount factor"""
    gae_lambda: float = 0.9
    """lambda of generalised advantage estimation"""
    clip_coef: float = 0.2
    """surrogate clipping coefficient"""
    ent_coef: float = 0.1
    """entropy coefficient"""
    # The table does not list these; ManiSkill's PPO baseline values.
    vf_coef: float = 0.5
    """value loss coefficient"""
    max_grad_norm: float = 0.5
    """gradient norm clip"""
    norm_adv: bool = True
    """normalise advantages per minibatch"""
    target_kl: float = 0.1
    """stop an update's epochs early once the approximate KL exceeds this (0 disables)"""
    hidden_sizes: tuple[int, ...] = (256, 256, 256)
    """hidden layer widths of the actor and of the critic (tanh MLPs)"""
    init_logstd: float = -0.5
    """initial log standard deviation of the Gaussian policy"""

    # Evaluation and checkpoints
    eval_freq: int = 25
    """evaluate (and checkpoint) every this many iterations, and at the end"""
    eval_episodes: int = 100
    """evaluation episodes per training condition (deterministic actions)"""
    eval_first_seed: int = 0
    """episode j of every condition is evaluated with seed eval_first_seed + j (as `vla-ladder eval` does)"""
    keep_checkpoints: int = 3
    """how many recent checkpoints to keep (checkpoints/best is always kept)"""

    def __post_init__(self):
        self.out = Path(self.out)
        self.hidden_sizes = tuple(self.hidden_sizes)
        if not isinstance(self.grid, ConditionGrid):
            self.grid = ConditionGrid(**self.grid)
        check_sim_backend(self.sim_backend)
        for f in fields(self):  # inf or nan trained a first rollout, then failed in torch with a tensor dump
            if f.type == "float" and not math.isfinite(getattr(self, f.name)):
                raise ValueError(f"--{f.name.replace('_', '-')} must be a finite number, got {getattr(self, f.name)}")
        positive = ("num_envs", "max_episode_steps", "num_steps", "num_minibatches", "update_epochs",
                    "eval_freq", "eval_episodes", "keep_checkpoints", "learning_rate", "torch_threads")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ValueError(f"--{name.replace('_', '-')} must be positive, got {getattr(self, name)}")
        for name in ("gamma", "gae_lambda"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"--{name.replace('_', '-')} must be in [0, 1], got {getattr(self, name)}")
        for name in ("clip_coef", "max_grad_norm", "vf_coef"):  # 0 would freeze the policy or the critic
            if not getattr(self, name) > 0:
                raise ValueError(f"--{name.replace('_', '-')} must be positive, got {getattr(self, name)}")
        for name in ("ent_coef", "target_kl", "weight_decay"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 0, got {getattr(self, name)}")
        if not self.hidden_sizes or min(self.hidden_sizes) <= 0:
            raise ValueError(f"--hidden-sizes must be positive widths, got {self.hidden_sizes}")
        check_seed(self.train_seed, "--train-seed")
        check_seed(self.eval_first_seed, "--eval-first-seed")
        if self.minibatch_size < 1:
            raise ValueError(f"--num-minibatches {self.num_minibatches} exceeds the batch of "
                             f"{self.batch_size} (num_envs x num_steps)")
        if self.minibatch_size < 2 and self.norm_adv:  # the std of one advantage is NaN, and so was every weight
            raise ValueError(f"--num-minibatches {self.num_minibatches} leaves minibatches of one step, whose "
                             f"advantages cannot be normalised; use at most {self.batch_size // 2}, or --no-norm-adv")
        if self.total_timesteps < self.batch_size:
            raise ValueError(f"--total-timesteps must be at least one batch (num_envs x num_steps = "
                             f"{self.batch_size}), got {self.total_timesteps}")
        if not 0 <= self.eval_first_seed <= TRAIN_SEED_MIN - self.eval_episodes:
            raise ValueError(f"evaluation seeds must stay below the training seeds ({TRAIN_SEED_MIN}): "
                             f"need 0 <= eval_first_seed <= {TRAIN_SEED_MIN - self.eval_episodes}")
        check_output_dir(self.out, "--out")
        if self.out.is_dir() and not self.resume:  # a run writes its files among others' and mixes with them
            foreign = sorted(p.name for p in self.out.iterdir()
                             if p.name not in RUN_FILES and not p.name.startswith("."))
            if foreign:
                raise ValueError(f"--out {str(self.out)!r} is not empty and holds no PPO run ({', '.join(foreign[:3])}"
                                 f"{', ...' if len(foreign) > 3 else ''}); use a new or empty --out")
        self._check_machine()

    def _check_machine(self) -> None:
        """The backend fits this machine: physx_cuda needs a CUDA GPU, physx_cpu runs a process per env."""
        if self.sim_backend == "physx_cuda":
            from vla_ladder.task.physx_gpu import check_physx_cuda
            check_physx_cuda(f"--sim-backend physx_cuda (the default: the paper's {self.num_envs} GPU envs) needs a "
                             f"CUDA GPU and none is visible; on this CPU machine pass --sim-backend physx_cpu "
                             f"--num-envs N (N <= {cores()}, one process each) and a --total-timesteps it can run "
                             "(about 80 env-steps/s with one env, 106 with two, on 2 cores)")
        elif self.num_envs > cores():
            raise ValueError(f"--sim-backend physx_cpu runs one process per env: --num-envs must be at most the "
                             f"{cores()} CPU cores here, got {self.num_envs}")

    @property
    def conditions(self) -> list[Condition]:
        """Every condition trained on (pairing splits skip full_random)."""
        return self.grid.conditions

    @property
    def batch_size(self) -> int:
        return self.num_envs * self.num_steps

    @property
    def minibatch_size(self) -> int:
        return self.batch_size // self.num_minibatches
