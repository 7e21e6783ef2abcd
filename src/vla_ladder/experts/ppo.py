"""PPO expert on privileged state for GraspObject-v1, in the CleanRL / ManiSkill-baseline style.

The agent sees the flat 96-d "state" observation (joint state, TCP pose, every object's pose, which
objects are present, a one-hot of the instructed object, grasp flags and the instructed grasp point),
so one policy serves every instruction. Defaults are the paper's appendix table.

Episodes always last `max_episode_steps` and never terminate (success is judged at the final step), so
every parallel env starts and ends its episodes together: the trainer resets all envs at once with
seeds it chooses (>= TRAIN_SEED_MIN, disjoint from evaluation seeds) and bootstraps the value of the
final observation at each truncation.

    vla-ladder train-expert --out runs/ppo                      # the paper's setting, on a GPU
    vla-ladder train-expert --out runs/ppo --resume             # continue from the last checkpoint
    vla-ladder train-expert --out /tmp/p --sim-backend physx_cpu --num-envs 1 --total-timesteps 500
"""

from __future__ import annotations

import argparse
import ast
import functools
import inspect
import itertools
import json
import shutil
import time
import typing
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
from safetensors import SafetensorError
from safetensors.torch import load_file, safe_open, save_file
from torch.distributions.normal import Normal

from vla_ladder import io
from vla_ladder.task.layouts import REGIMES, SPLITS, check_args

# Training episodes take seeds in [TRAIN_SEED_MIN, 2**32) (numpy's seed limit); evaluation seeds stay
# below, so `vla-ladder eval --seed S` with any S + episodes <= TRAIN_SEED_MIN is held out.
TRAIN_SEED_MIN = 2**30
FORMAT = "vla-ladder-ppo/1"
SIM_BACKENDS = ("physx_cuda", "physx_cpu")


@dataclass
class Args:
    out: str = ""
    """directory of the run: config.json, state.json, checkpoints/, evals.json, tb/ (TensorBoard)"""
    resume: bool = False
    """continue the run in --out from its last checkpoint (same step count and optimizer state)"""
    seed: int = 1
    """seed of the experiment (network init, action sampling, training episode seeds)"""
    cuda: bool = True
    """run the networks on CUDA when available (always the case with physx_cuda)"""
    progress: bool = True
    """show a progress bar"""
    torch_threads: int = 1
    """CPU threads for the networks when they run on the CPU (their batches are small and the simulator
    needs the cores: 2 threads on a busy 2-core machine made each forward pass ~50x slower)"""

    # Environment
    sim_backend: str = "physx_cuda"
    """physx_cuda (GPU-parallel envs) or physx_cpu (one env in-process, several through AsyncVectorEnv)"""
    num_envs: int = 1024
    """the number of parallel environments"""
    max_episode_steps: int = 50
    """episode length in control steps (20 Hz)"""
    regimes: tuple[str, ...] = tuple(REGIMES)
    """placement regimes to train on (a mixture: env slots cycle through every condition)"""
    splits: tuple[str, ...] = ("canonical",)
    """object-region splits to train on (pairing splits combine only with jitter regimes)"""
    num_objects: tuple[int, ...] = (1, 3, 5)
    """object counts to train on"""

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
    eval_seed: int = 0
    """episode j of every condition is evaluated with seed eval_seed + j (as `vla-ladder eval` does)"""
    keep_checkpoints: int = 3
    """how many recent checkpoints to keep (checkpoints/best is always kept)"""

    def __post_init__(self):
        self.regimes, self.splits = tuple(self.regimes), tuple(self.splits)
        self.num_objects, self.hidden_sizes = tuple(self.num_objects), tuple(self.hidden_sizes)
        if not self.out:
            raise ValueError("--out DIR is required")
        if self.sim_backend not in SIM_BACKENDS:
            raise ValueError(f"unknown sim backend {self.sim_backend!r}; allowed: {', '.join(SIM_BACKENDS)}")
        for r in self.regimes:
            check_args(r)
        for s in self.splits:
            if s not in SPLITS:
                raise ValueError(f"unknown split {s!r}; allowed: {', '.join(SPLITS)}")
        for k in self.num_objects:
            check_args(next(iter(REGIMES)), num_objects=k)
        if not self.conditions:
            raise ValueError("no valid condition: pairing splits need a jitter regime "
                             f"({', '.join(r for r, e in REGIMES.items() if e is not None)})")
        positive = ("num_envs", "max_episode_steps", "num_steps", "num_minibatches", "update_epochs",
                    "eval_freq", "eval_episodes", "keep_checkpoints", "learning_rate", "torch_threads")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ValueError(f"--{name.replace('_', '-')} must be positive, got {getattr(self, name)}")
        if not self.hidden_sizes or min(self.hidden_sizes) <= 0:
            raise ValueError(f"--hidden-sizes must be positive widths, got {self.hidden_sizes}")
        if self.minibatch_size < 1:
            raise ValueError(f"--num-minibatches {self.num_minibatches} exceeds the batch of "
                             f"{self.batch_size} (num_envs x num_steps)")
        if self.total_timesteps < self.batch_size:
            raise ValueError(f"--total-timesteps must be at least one batch (num_envs x num_steps = "
                             f"{self.batch_size}), got {self.total_timesteps}")
        if not 0 <= self.eval_seed <= TRAIN_SEED_MIN - self.eval_episodes:
            raise ValueError(f"evaluation seeds must stay below the training seeds ({TRAIN_SEED_MIN}): "
                             f"need 0 <= eval_seed <= {TRAIN_SEED_MIN - self.eval_episodes}")

    @property
    def conditions(self) -> list[tuple[str, str, int]]:
        """Every (regime, split, num_objects) trained on; pairing splits skip full_random."""
        return [(r, s, int(k)) for r, s, k in itertools.product(self.regimes, self.splits, self.num_objects)
                if s == "canonical" or REGIMES[r] is not None]

    @property
    def batch_size(self) -> int:
        return self.num_envs * self.num_steps

    @property
    def minibatch_size(self) -> int:
        return self.batch_size // self.num_minibatches

    @property
    def num_iterations(self) -> int:
        return self.total_timesteps // self.batch_size


# ---------------------------------------------------------------------------------------------- agent
def layer_init(layer: nn.Linear, std: float = np.sqrt(2), bias_const: float = 0.0) -> nn.Linear:
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


def mlp(sizes: list[int], out_std: float) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(sizes[:-2], sizes[1:-1]):
        layers += [layer_init(nn.Linear(a, b)), nn.Tanh()]
    return nn.Sequential(*layers, layer_init(nn.Linear(sizes[-2], sizes[-1]), std=out_std))


class Agent(nn.Module):
    """Tanh MLP critic and Gaussian actor with a state-independent standard deviation."""

    def __init__(self, obs_dim: int, act_dim: int, hidden_sizes=(256, 256, 256), init_logstd: float = -0.5):
        super().__init__()
        self.obs_dim, self.act_dim, self.hidden_sizes = int(obs_dim), int(act_dim), tuple(hidden_sizes)
        self.critic = mlp([obs_dim, *hidden_sizes, 1], out_std=1.0)
        self.actor_mean = mlp([obs_dim, *hidden_sizes, act_dim], out_std=0.01 * np.sqrt(2))
        self.actor_logstd = nn.Parameter(torch.full((1, act_dim), float(init_logstd)))

    def get_value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x).squeeze(-1)

    def get_action(self, x: torch.Tensor, deterministic: bool = False) -> torch.Tensor:
        mean = self.actor_mean(x)
        return mean if deterministic else Normal(mean, self.actor_logstd.exp().expand_as(mean)).sample()

    def get_action_and_value(self, x: torch.Tensor, action: torch.Tensor | None = None):
        mean = self.actor_mean(x)
        probs = Normal(mean, self.actor_logstd.exp().expand_as(mean))
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action).sum(1), probs.entropy().sum(1), self.get_value(x)


# ------------------------------------------------------------------------------- advantage and loss
def compute_gae(rewards: torch.Tensor, values: torch.Tensor, next_values: torch.Tensor, dones: torch.Tensor,
                gamma: float, gae_lambda: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalised advantage estimates and returns over a (T, N) rollout.

    next_values[t] is V of the state transition t led to: for a transition that ended its episode by
    truncation it is V(final observation), so the target still bootstraps (no episode here terminates).
    dones[t] = 1 stops the advantage trace there, since step t + 1 belongs to a new episode.
    """
    advantages = torch.zeros_like(rewards)
    lastgaelam = torch.zeros_like(rewards[0])
    for t in reversed(range(rewards.shape[0])):
        delta = rewards[t] + gamma * next_values[t] - values[t]
        lastgaelam = delta + gamma * gae_lambda * (1.0 - dones[t]) * lastgaelam
        advantages[t] = lastgaelam
    return advantages, advantages + values


def ppo_loss(newlogprob: torch.Tensor, oldlogprob: torch.Tensor, advantages: torch.Tensor,
             newvalue: torch.Tensor, returns: torch.Tensor, entropy: torch.Tensor, clip_coef: float,
             vf_coef: float, ent_coef: float, norm_adv: bool = True) -> tuple[torch.Tensor, dict]:
    """The clipped PPO objective (to minimise) and its parts, for one minibatch."""
    logratio = newlogprob - oldlogprob
    ratio = logratio.exp()
    if norm_adv:
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    pg_loss = torch.max(-advantages * ratio, -advantages * torch.clamp(ratio, 1 - clip_coef, 1 + clip_coef)).mean()
    v_loss = 0.5 * ((newvalue - returns) ** 2).mean()
    entropy_loss = entropy.mean()
    loss = pg_loss - ent_coef * entropy_loss + vf_coef * v_loss
    with torch.no_grad():  # http://joschu.net/blog/kl-approx.html
        stats = dict(pg_loss=pg_loss.item(), v_loss=v_loss.item(), entropy=entropy_loss.item(),
                     approx_kl=((ratio - 1) - logratio).mean().item(),
                     clipfrac=((ratio - 1.0).abs() > clip_coef).float().mean().item())
    return loss, stats


# -------------------------------------------------------------------------------------- environments
class SlotEnv(gym.Wrapper):
    """One CPU env of an AsyncVectorEnv: AsyncVectorEnv sends every sub-env the same reset options,
    so each picks its own row of the batched "conditions"."""

    def __init__(self, env: gym.Env, index: int):
        super().__init__(env)
        self.index = index

    def reset(self, *, seed=None, options=None):
        options = dict(options or {})
        if "conditions" in options:
            options["conditions"] = [options["conditions"][self.index]]
        return self.env.reset(seed=seed, options=options)


def make_cpu_env(index: int, **make_kwargs) -> gym.Env:
    """Build sub-env `index` in a spawned process (module-level, so it pickles)."""
    from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper

    import vla_ladder.task.env  # noqa: F401  (registers GraspObject-v1 in this process)

    return SlotEnv(CPUGymWrapper(gym.make("GraspObject-v1", **make_kwargs), ignore_terminations=True), index)


class TrainEnvs:
    """num_envs GraspObject-v1 episodes in lockstep, as torch tensors on `device`: one GPU env
    (ManiSkillVectorEnv), one CPU env, or several CPU envs in spawned processes (AsyncVectorEnv)."""

    def __init__(self, args: Args, device: torch.device):
        import vla_ladder.task.env  # noqa: F401

        self.num_envs, self.device = args.num_envs, device
        kw = dict(obs_mode="state", control_mode="pd_ee_delta_pose", reward_mode="normalized_dense",
                  sim_backend=args.sim_backend, max_episode_steps=args.max_episode_steps)
        self._async = args.sim_backend == "physx_cpu" and args.num_envs > 1
        if self._async:
            self.env = gym.vector.AsyncVectorEnv(
                [functools.partial(make_cpu_env, i, **kw) for i in range(args.num_envs)], context="spawn",
                autoreset_mode=gym.vector.AutoresetMode.DISABLED)
        else:
            from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv
            self.env = ManiSkillVectorEnv(gym.make("GraspObject-v1", num_envs=args.num_envs, **kw),
                                          auto_reset=False, ignore_terminations=True)
        self.obs_dim = int(np.prod(self.env.single_observation_space.shape))
        self.act_dim = int(np.prod(self.env.single_action_space.shape))

    @property
    def object_set(self) -> str:
        return self.env.get_attr("object_set")[0] if self._async else self.env.unwrapped.object_set

    def _t(self, x) -> torch.Tensor:
        return torch.as_tensor(np.asarray(x) if self._async else x).to(self.device)

    def reset(self, seeds: list[int], conditions: list[tuple[str, str, int]]) -> torch.Tensor:
        obs, _ = self.env.reset(seed=[int(s) for s in seeds], options={"conditions": conditions})
        return self._t(obs).float()

    def step(self, action: torch.Tensor):
        """obs, reward, truncated and the final-step metrics (success, grasp_any, reach)."""
        a = action.cpu().numpy() if self._async else action.to(self.env.device)
        obs, reward, _, truncated, info = self.env.step(a)
        metrics = {k: self._t(info[k]).bool() for k in ("success", "grasp_any", "reach")}
        return self._t(obs).float(), self._t(reward).float(), self._t(truncated).bool(), metrics

    def close(self):
        self.env.close()


def slot_conditions(conditions: list, num_envs: int, round_: int) -> list:
    """Env slot i plays conditions[(i + round_ * num_envs) % K]: an even mixture over time even when
    the conditions outnumber the envs."""
    return [conditions[(i + round_ * num_envs) % len(conditions)] for i in range(num_envs)]


def train_seeds(seed: int, round_: int, n: int) -> list[int]:
    """Episode seeds of the round_-th training reset: a pure function, so --resume replays none."""
    return np.random.default_rng([seed, round_]).integers(TRAIN_SEED_MIN, 2**32, n).tolist()


def evaluate(agent: Agent, envs: TrainEnvs, args: Args) -> dict:
    """Deterministic episodes on held-out seeds: eval_episodes per condition, rates per condition."""
    import pandas as pd

    from vla_ladder.evaluation.metrics import rates

    jobs = [(c, j) for c in args.conditions for j in range(args.eval_episodes)]
    rows = []
    for start in range(0, len(jobs), envs.num_envs):
        chunk = jobs[start:start + envs.num_envs]
        pad = chunk + [chunk[-1]] * (envs.num_envs - len(chunk))  # spare envs replay a job, ignored
        obs = envs.reset([args.eval_seed + j for _, j in pad], [c for c, _ in pad])
        for _ in range(args.max_episode_steps):
            with torch.no_grad():
                action = agent.get_action(obs, deterministic=True).clamp(-1, 1)
            obs, _, truncated, metrics = envs.step(action)
        if not truncated.all():
            raise RuntimeError("evaluation episodes fell out of lockstep")
        for i, (cond, j) in enumerate(chunk):
            rows.append({"regime": cond[0], "split": cond[1], "num_objects": cond[2], "episode": j,
                         **{m: bool(v[i]) for m, v in metrics.items()}})
    df = pd.DataFrame(rows)
    per_cond = {f"{r}/{s}/{k}": rates(g) for (r, s, k), g in df.groupby(["regime", "split", "num_objects"],
                                                                      sort=False)}
    return {"all": rates(df), "conditions": per_cond}


# ------------------------------------------------------------------------------------- checkpoints
def save_agent(path: Path, agent: Agent) -> None:
    meta = {"format": FORMAT, "obs_dim": str(agent.obs_dim), "act_dim": str(agent.act_dim),
            "hidden_sizes": ",".join(map(str, agent.hidden_sizes))}
    with io.atomic_path(path) as tmp:
        save_file({k: v.detach().cpu().contiguous() for k, v in agent.state_dict().items()}, str(tmp), meta)


def checkpoint_dir(path: str | Path) -> Path:
    """The checkpoint a path names: a checkpoint directory, or a run directory's latest checkpoint."""
    p = Path(path)
    if (p / "model.safetensors").is_file():
        return p
    if (p / "state.json").is_file():
        try:
            return p / json.loads((p / "state.json").read_text())["checkpoint"]
        except (ValueError, KeyError) as e:
            raise ValueError(f"unreadable PPO run state {p / 'state.json'}: {e}") from e
    raise ValueError(f"no PPO checkpoint at {str(path)!r}: expected a run directory with state.json "
                     "or a checkpoint directory with model.safetensors")


def load_agent(path: str | Path, obs_dim: int | None = None, act_dim: int | None = None,
               device: str | torch.device = "cpu") -> Agent:
    """Load model.safetensors of a checkpoint (or run) directory; ValueError when it is unreadable or
    was trained for other observation/action sizes than the ones given."""
    f = checkpoint_dir(path) / "model.safetensors"
    try:
        with safe_open(str(f), framework="pt") as sf:
            meta = sf.metadata() or {}
        if meta.get("format") != FORMAT:
            raise ValueError(f"format {meta.get('format')!r}, expected {FORMAT!r}")
        agent = Agent(int(meta["obs_dim"]), int(meta["act_dim"]), [int(h) for h in meta["hidden_sizes"].split(",")])
        agent.load_state_dict(load_file(str(f)))
    except (SafetensorError, OSError, KeyError, ValueError, RuntimeError) as e:
        raise ValueError(f"unreadable PPO checkpoint {f}: {e}") from e
    if (obs_dim is not None and obs_dim != agent.obs_dim) or (act_dim is not None and act_dim != agent.act_dim):
        raise ValueError(f"PPO checkpoint {f} was trained for {agent.obs_dim}-d observations and "
                         f"{agent.act_dim}-d actions; this environment has {obs_dim}-d observations and "
                         f"{act_dim}-d actions")
    return agent.to(device)


def save_optimizer(path: Path, optimizer: torch.optim.Optimizer) -> None:
    sd = optimizer.state_dict()
    tensors = {f"state.{pid}.{k}": torch.as_tensor(v).detach().cpu().contiguous()
               for pid, st in sd["state"].items() for k, v in st.items()}
    with io.atomic_path(path) as tmp:
        save_file(tensors, str(tmp), {"param_groups": json.dumps(sd["param_groups"])})


def load_optimizer(path: Path, optimizer: torch.optim.Optimizer) -> None:
    try:
        with safe_open(str(path), framework="pt") as sf:
            groups = json.loads(sf.metadata()["param_groups"])
            state: dict[int, dict] = {}
            for key in sf.keys():
                _, pid, name = key.split(".", 2)
                state.setdefault(int(pid), {})[name] = sf.get_tensor(key)
        optimizer.load_state_dict({"state": state, "param_groups": groups})
    except (SafetensorError, OSError, KeyError, ValueError, RuntimeError) as e:
        raise ValueError(f"unreadable optimizer state {path}: {e}") from e


def save_checkpoint(out: Path, agent: Agent, optimizer: torch.optim.Optimizer, state: dict, keep: int,
                    best: bool) -> None:
    """Write checkpoints/step_N/ in full, then point state.json at it: a crash leaves the previous
    checkpoint in charge."""
    name = f"checkpoints/step_{state['global_step']:012d}"
    ck = out / name
    save_agent(ck / "model.safetensors", agent)
    save_optimizer(ck / "optimizer.safetensors", optimizer)
    io.write_json(ck / "state.json", state)
    if best:
        best_dir = out / "checkpoints" / "best"
        save_agent(best_dir / "model.safetensors", agent)
        io.write_json(best_dir / "state.json", state)
    io.write_json(out / "state.json", {**state, "checkpoint": name})
    for old in sorted((out / "checkpoints").glob("step_*"))[:-keep]:
        shutil.rmtree(old)


# ------------------------------------------------------------------------------------------ training
def train(args: Args) -> dict:
    """Train (or resume) a PPO expert; returns the final training state."""
    from torch.utils.tensorboard import SummaryWriter
    from tqdm.auto import tqdm

    out = Path(args.out)
    if (out / "state.json").exists() and not args.resume:
        raise ValueError(f"{out} already holds a run; pass --resume to continue it or choose another --out")
    state = {"global_step": 0, "iteration": 0, "train_resets": 0, "wall_s": 0.0, "best_success": -1.0,
             "eval": None}
    if args.resume:
        if not (out / "state.json").exists():
            raise ValueError(f"--resume: no run to continue in {out} (state.json missing)")
        state.update(json.loads((out / "state.json").read_text()))
    cuda = args.sim_backend == "physx_cuda" or (args.cuda and torch.cuda.is_available())
    device = torch.device("cuda" if cuda else "cpu")
    if not cuda:
        torch.set_num_threads(args.torch_threads)
    torch.manual_seed(args.seed + state["iteration"])  # a resumed run draws fresh, reproducible noise
    np.random.seed(args.seed + state["iteration"])

    envs = TrainEnvs(args, device)
    agent = Agent(envs.obs_dim, envs.act_dim, args.hidden_sizes, args.init_logstd).to(device)
    optimizer = torch.optim.AdamW(agent.parameters(), lr=args.learning_rate, weight_decay=args.weight_decay,
                                  eps=1e-5)
    if args.resume:
        ck = checkpoint_dir(out)
        agent.load_state_dict(load_agent(ck, envs.obs_dim, envs.act_dim).state_dict())
        load_optimizer(ck / "optimizer.safetensors", optimizer)
        for group in optimizer.param_groups:  # overrides given with --resume win over the saved ones
            group.update(lr=args.learning_rate, weight_decay=args.weight_decay)
    io.write_json(out / "config.json", {**asdict(args), "conditions": args.conditions, "obs_dim": envs.obs_dim,
                                        "act_dim": envs.act_dim, "provenance": io.provenance(envs.object_set)})
    writer = SummaryWriter(str(out / "tb"), purge_step=state["global_step"] or None)
    evals = json.loads((out / "evals.json").read_text()) if args.resume and (out / "evals.json").exists() else []

    T, N = args.num_steps, args.num_envs
    obs = torch.zeros((T, N, envs.obs_dim), device=device)
    actions = torch.zeros((T, N, envs.act_dim), device=device)
    logprobs, rewards, dones, values, final_values = (torch.zeros((T, N), device=device) for _ in range(5))

    def new_episodes() -> torch.Tensor:
        r = state["train_resets"]
        state["train_resets"] += 1
        return envs.reset(train_seeds(args.seed, r, N), slot_conditions(args.conditions, N, r))

    def eval_and_checkpoint() -> None:
        result = evaluate(agent, envs, args)
        state["eval"] = {"global_step": state["global_step"], "wall_s": round(state["wall_s"], 1), **result}
        evals.append(state["eval"])
        io.write_json(out / "evals.json", evals)
        for m in ("success", "grasp_any", "reach"):
            writer.add_scalar(f"eval/{m}", result["all"][m], state["global_step"])
            for cond, r in result["conditions"].items():
                writer.add_scalar(f"eval_{m}/{cond}", r[m], state["global_step"])
        best = result["all"]["success"] > state["best_success"]
        if best:
            state["best_success"] = result["all"]["success"]
        save_checkpoint(out, agent, optimizer, state, args.keep_checkpoints, best)
        bar.write(f"step {state['global_step']}: eval success {result['all']['success']:.3f} "
                  f"grasp_any {result['all']['grasp_any']:.3f} reach {result['all']['reach']:.3f}")

    bar = tqdm(total=args.num_iterations * args.batch_size, initial=state["global_step"], unit="step",
               disable=not args.progress, dynamic_ncols=True)
    next_obs = new_episodes()
    ep_return = torch.zeros(N, device=device)
    sps = 0.0
    try:
        for iteration in range(state["iteration"] + 1, args.num_iterations + 1):
            t0 = time.perf_counter()
            finished = {"success": [], "grasp_any": [], "reach": [], "return": []}
            for step in range(T):
                obs[step] = next_obs
                with torch.no_grad():
                    action, logprob, _, value = agent.get_action_and_value(next_obs)
                values[step], actions[step], logprobs[step] = value, action, logprob
                next_obs, reward, truncated, metrics = envs.step(action.clamp(-1, 1))
                rewards[step] = reward
                ep_return += reward
                dones[step] = truncated.float()
                if truncated.any():
                    if not truncated.all():
                        raise RuntimeError("envs fell out of lockstep")
                    with torch.no_grad():
                        final_values[step] = agent.get_value(next_obs)  # bootstrap the truncation
                    for m, v in metrics.items():
                        finished[m].append(v.float().mean().item())
                    finished["return"].append(ep_return.mean().item())
                    ep_return.zero_()
                    next_obs = new_episodes()
            with torch.no_grad():
                # A transition that ended its episode bootstraps from the final observation, any other from
                # the next stored value (or, at the end of the rollout, the value of the current observation).
                following = torch.cat([values[1:], agent.get_value(next_obs)[None]], dim=0)
                next_values = torch.where(dones.bool(), final_values, following)
                advantages, returns = compute_gae(rewards, values, next_values, dones, args.gamma, args.gae_lambda)
            t_rollout = time.perf_counter() - t0

            b_obs, b_actions = obs.reshape(-1, envs.obs_dim), actions.reshape(-1, envs.act_dim)
            b_logprobs, b_adv, b_returns = logprobs.reshape(-1), advantages.reshape(-1), returns.reshape(-1)
            stats: dict[str, list[float]] = {}
            for _ in range(args.update_epochs):
                perm = torch.randperm(args.batch_size, device=device)
                for start in range(0, args.batch_size - args.minibatch_size + 1, args.minibatch_size):
                    mb = perm[start:start + args.minibatch_size]
                    _, newlogprob, entropy, newvalue = agent.get_action_and_value(b_obs[mb], b_actions[mb])
                    loss, s = ppo_loss(newlogprob, b_logprobs[mb], b_adv[mb], newvalue, b_returns[mb], entropy,
                                       args.clip_coef, args.vf_coef, args.ent_coef, args.norm_adv)
                    optimizer.zero_grad()
                    loss.backward()
                    nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                    optimizer.step()
                    for k, v in s.items():
                        stats.setdefault(k, []).append(v)
                if args.target_kl and stats["approx_kl"][-1] > args.target_kl:
                    break

            dt = time.perf_counter() - t0
            state["global_step"] += args.batch_size
            state["iteration"] = iteration
            state["wall_s"] += dt
            sps = args.batch_size / dt
            gs = state["global_step"]
            for k, v in stats.items():
                writer.add_scalar(f"losses/{k}", float(np.mean(v)), gs)
            y = b_returns.var()
            writer.add_scalar("losses/explained_variance",
                              float("nan") if y == 0 else (1 - (b_returns - values.reshape(-1)).var() / y).item(), gs)
            writer.add_scalar("charts/SPS", sps, gs)
            writer.add_scalar("charts/rollout_SPS", args.batch_size / t_rollout, gs)
            writer.add_scalar("charts/std", agent.actor_logstd.exp().mean().item(), gs)
            for k, v in finished.items():
                if v:
                    writer.add_scalar(f"train/{k}", float(np.mean(v)), gs)
            bar.update(args.batch_size)
            post = {"SPS": f"{sps:.0f}"}
            if finished["success"]:
                post["train_success"] = f"{np.mean(finished['success']):.2f}"
            if state["eval"]:
                post["eval_success"] = f"{state['eval']['all']['success']:.2f}"
            bar.set_postfix(post)
            if iteration % args.eval_freq == 0 or iteration == args.num_iterations:
                eval_and_checkpoint()
                next_obs = new_episodes()
                ep_return.zero_()
    finally:
        bar.close()
        writer.close()
        envs.close()
    return {**state, "sps": sps}


# ----------------------------------------------------------------------------------------------- CLI
def _field_docs(cls) -> dict[str, str]:
    """The docstring under each dataclass field (the CleanRL / tyro convention)."""
    body = ast.parse(inspect.getsource(cls)).body[0].body
    return {a.target.id: b.value.value for a, b in zip(body, body[1:])
            if isinstance(a, ast.AnnAssign) and isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    docs, hints = _field_docs(Args), typing.get_type_hints(Args)
    for f in fields(Args):
        flag, hint = "--" + f.name.replace("_", "-"), hints[f.name]
        default = " ".join(map(str, f.default)) if isinstance(f.default, tuple) else f.default
        help_ = f"{docs.get(f.name, '')} (default: {default})"
        # SUPPRESS keeps unset options out of the namespace, so --resume can tell overrides from defaults.
        if f.name == "out":
            parser.add_argument(flag, required=True, metavar="DIR", default=argparse.SUPPRESS, help=docs[f.name])
        elif hint is bool:
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=argparse.SUPPRESS, help=help_)
        elif typing.get_origin(hint) is tuple:
            parser.add_argument(flag, nargs="+", type=typing.get_args(hint)[0], default=argparse.SUPPRESS,
                                metavar=f.name.upper().rstrip("S") or None, help=help_)
        else:
            parser.add_argument(flag, type=hint, default=argparse.SUPPRESS, help=help_)


def args_from_namespace(ns: argparse.Namespace) -> Args:
    """Args from the options given; with --resume, the run's saved config fills in the rest."""
    given = {f.name: getattr(ns, f.name) for f in fields(Args) if hasattr(ns, f.name)}
    if given.get("resume") and given.get("out") and (Path(given["out"]) / "config.json").exists():
        saved = json.loads((Path(given["out"]) / "config.json").read_text())
        given = {**{f.name: saved[f.name] for f in fields(Args) if f.name in saved}, **given}
    return Args(**given)


def run(ns: argparse.Namespace) -> int:
    args = args_from_namespace(ns)
    result = train(args)
    ev = result["eval"]["all"] if result.get("eval") else {}
    print(json.dumps({"out": args.out, "global_step": result["global_step"], "sps": round(result["sps"], 1),
                      **{m: ev.get(m) for m in ("success", "grasp_any", "reach")}}))
    return 0


if __name__ == "__main__":
    import sys

    from vla_ladder.cli import main

    sys.exit(main(["train-expert", *sys.argv[1:]]))
