"""PPO expert on privileged state for GraspObject-v1, in the CleanRL / ManiSkill-baseline style: the
training loop, read top to bottom (Args in config.py, the maths in loss.py, the envs in envs.py, the
checkpoint files in checkpoint.py, the network in vla_ladder.policies.ppo).

Every parallel env starts and ends its episodes together (they never terminate early), so the loop resets
all envs at once with seeds it chooses and bootstraps the value of the final observation at each
truncation.

    vla-ladder train-expert --out runs/ppo                      # the paper's setting, on a GPU
    vla-ladder train-expert --out runs/ppo --resume             # continue from the last checkpoint
    vla-ladder train-expert --out /tmp/p --sim-backend physx_cpu --num-envs 1 --total-timesteps 500
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn

from vla_ladder import files
from vla_ladder.conditions import ConditionGrid
from vla_ladder.contract import METRICS
from vla_ladder.policies.ppo import Agent, checkpoint_dir, load_agent
from vla_ladder.ppo.checkpoint import load_optimizer, load_run_state, save_checkpoint
from vla_ladder.ppo.config import Args
from vla_ladder.ppo.envs import TrainEnvs, slot_conditions, train_seeds
from vla_ladder.ppo.loss import compute_gae, ppo_loss
from vla_ladder.stats import rates
from vla_ladder.task.layouts import sample_layout
from vla_ladder.task.objects import OBJECT_NAMES


def noise_seed(train_seed: int, iteration: int) -> int:
    """The seed of torch's and NumPy's generators (action noise, minibatch order) for a run started at
    `iteration`: train_seed itself for a fresh run, and for a resumed one a hash of both, so that a resume draws
    fresh, reproducible noise that is no other run's (with train_seed + iteration, a run of seed 0 resumed at
    iteration 1 drew the noise of a fresh run of seed 1)."""
    if iteration == 0:
        return train_seed
    return int(np.random.SeedSequence([train_seed, iteration]).generate_state(1)[0])


def summary_writer(out: Path, global_step: int):
    """TensorBoard's writer for the run in `out`, resumed at `global_step`: a killed run's points past the checkpoint
    are purged (the resumed run logs them again), the checkpoint's own kept. Its losses and evaluation were logged at
    global_step before it was saved; purge_step=global_step dropped them, and the curve lost its last evaluation."""
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(str(out / "tb"), purge_step=global_step + 1 if global_step else None)


def evaluate(agent: Agent, envs: TrainEnvs, args: Args) -> dict:
    """Deterministic episodes on held-out seeds: eval_episodes per condition; rates in all, per condition and per
    instructed object (an expert that never grasps an object records no episode instructing it)."""
    import pandas as pd

    jobs = [(c, j) for c in args.conditions for j in range(args.eval_episodes)]
    rows = []
    for start in range(0, len(jobs), envs.num_envs):
        chunk = jobs[start:start + envs.num_envs]
        pad = chunk + [chunk[-1]] * (envs.num_envs - len(chunk))  # spare envs replay a job, ignored
        obs = envs.reset([args.eval_first_seed + j for _, j in pad], [c for c, _ in pad])
        for _ in range(args.max_episode_steps):
            with torch.no_grad():
                action = agent.get_action(obs, deterministic=True).clamp(-1, 1)
            obs, _, truncated, metrics = envs.step(action)
        if not truncated.all():
            raise RuntimeError("evaluation episodes fell out of lockstep")
        for i, (cond, j) in enumerate(chunk):
            target = sample_layout(cond, args.eval_first_seed + j).target  # the seed's, as the env drew it
            rows.append({"condition": cond.key, "episode": j, "target": target,
                         **{m: bool(v[i]) for m, v in metrics.items()}})
    df = pd.DataFrame(rows)
    per_cond = {key: rates(g) for key, g in df.groupby("condition", sort=False)}
    per_target = {name: rates(g) for name, g in df.groupby("target")}
    return {"all": rates(df), "conditions": per_cond,
            "targets": {name: per_target[name] for name in OBJECT_NAMES if name in per_target}}


# ------------------------------------------------------------------------------------------ training
def train(args: Args) -> dict:
    """Train (or resume) a PPO expert; returns the final training state."""
    from tqdm.auto import tqdm

    out = args.out
    if (out / "state.json").exists() and not args.resume:
        raise ValueError(f"{out} already holds a run; pass --resume to continue it or choose another --out")
    state = {"global_step": 0, "iteration": 0, "train_resets": 0, "wall_s": 0.0, "best_success": -1.0,
             "eval": None}
    if args.resume:
        if not (out / "state.json").exists():
            raise ValueError(f"--resume: no run to continue in {out} (state.json missing)")
        state.update(load_run_state(out))
        saved = load_agent(checkpoint_dir(out))  # before any env starts: a network of other sizes cannot go on
        if saved.hidden_sizes != args.hidden_sizes:
            raise ValueError(f"--resume: the run's network has hidden sizes {list(saved.hidden_sizes)}, not "
                             f"{list(args.hidden_sizes)}; resume without --hidden-sizes, or train into a new --out")
    cuda = args.sim_backend == "physx_cuda" or (args.cuda and torch.cuda.is_available())
    device = torch.device("cuda" if cuda else "cpu")
    if not cuda:
        torch.set_num_threads(args.torch_threads)
    seed = noise_seed(args.train_seed, state["iteration"])
    torch.manual_seed(seed)
    np.random.seed(seed)

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
    files.write_json(out / "config.json", {**asdict(args), "conditions": [c.key for c in args.conditions],
                                           "obs_dim": envs.obs_dim, "act_dim": envs.act_dim,
                                           "provenance": files.provenance(envs.object_set)})
    writer = summary_writer(out, state["global_step"])
    evals = json.loads((out / "evals.json").read_text()) if args.resume and (out / "evals.json").exists() else []
    # evals.json is written just before its checkpoint: a run killed between the two has an evaluation the resumed
    # run makes again.
    evals = [e for e in evals if e["global_step"] <= state["global_step"]]

    T, N = args.num_steps, args.num_envs
    obs = torch.zeros((T, N, envs.obs_dim), device=device)
    actions = torch.zeros((T, N, envs.act_dim), device=device)
    logprobs, rewards, dones, values, final_values = (torch.zeros((T, N), device=device) for _ in range(5))

    def new_episodes() -> torch.Tensor:
        r = state["train_resets"]
        state["train_resets"] += 1
        return envs.reset(train_seeds(args.train_seed, r, N), slot_conditions(args.conditions, N, r))

    def eval_and_checkpoint() -> None:
        result = evaluate(agent, envs, args)
        state["eval"] = {"global_step": state["global_step"], "wall_s": round(state["wall_s"], 1), **result}
        evals.append(state["eval"])
        files.write_json(out / "evals.json", evals)
        for m in METRICS:
            writer.add_scalar(f"eval/{m}", result["all"][m], state["global_step"])
            for cond, r in result["conditions"].items():
                writer.add_scalar(f"eval_{m}/{cond}", r[m], state["global_step"])
            for name, r in result["targets"].items():
                writer.add_scalar(f"eval_{m}_by_target/{name}", r[m], state["global_step"])
        best = result["all"]["success"] > state["best_success"]
        if best:
            state["best_success"] = result["all"]["success"]
        save_checkpoint(out, agent, optimizer, state, args.keep_checkpoints, best,
                        selected_on={"first_seed": args.eval_first_seed, "episodes": args.eval_episodes,
                                     "conditions": [c.key for c in args.conditions]})
        by_target = ", ".join(f"{name} {round(r['success'] * r['n'])}/{r['n']}"
                              for name, r in result["targets"].items())
        bar.write(f"step {state['global_step']}: eval " + " ".join(f"{m} {result['all'][m]:.3f}" for m in METRICS)
                  + f" | success by target: {by_target}")

    # Counted in steps, not iterations: a resumed run may change the batch (--num-envs, --num-steps), which would
    # change what its saved iteration count means.
    last_iteration = state["iteration"] + max(0, args.total_timesteps - state["global_step"]) // args.batch_size
    bar = tqdm(total=state["global_step"] + (last_iteration - state["iteration"]) * args.batch_size,
               initial=state["global_step"], unit="step", disable=not args.progress, dynamic_ncols=True)
    next_obs = new_episodes()
    ep_return = torch.zeros(N, device=device)
    sps = 0.0
    try:
        for iteration in range(state["iteration"] + 1, last_iteration + 1):
            t0 = time.perf_counter()
            finished = {**{m: [] for m in METRICS}, "return": []}
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
            stats: dict[str, list[torch.Tensor]] = {}
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
                if args.target_kl and stats["approx_kl"][-1].item() > args.target_kl:  # (a sync an epoch)
                    break

            dt = time.perf_counter() - t0
            state["global_step"] += args.batch_size
            state["iteration"] = iteration
            state["wall_s"] += dt
            sps = args.batch_size / dt
            gs = state["global_step"]
            means = torch.stack([torch.stack(v).mean() for v in stats.values()]).tolist()  # one sync
            for k, mean in zip(stats, means):
                writer.add_scalar(f"losses/{k}", mean, gs)
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
            if iteration % args.eval_freq == 0 or iteration == last_iteration:
                eval_and_checkpoint()
                next_obs = new_episodes()
                ep_return.zero_()
    finally:
        bar.close()
        writer.close()
        envs.close()
    return {**state, "sps": sps}


# ----------------------------------------------------------------------------------------------- CLI
def cli_config(argv: list[str]) -> Args:
    """Args from the command line; with --resume, the run's saved config.json supplies every flag not given."""
    from vla_ladder.commandline import parse_config, unchecked

    prog, help_ = "vla-ladder train-expert", Args.__doc__.splitlines()[0]
    default = None
    out = next((v for flag, v in zip(argv, argv[1:]) if flag == "--out"),
               next((a.split("=", 1)[1] for a in argv if a.startswith("--out=")), None))
    if "--resume" in argv and out is not None and (Path(out) / "config.json").is_file():
        data = json.loads((Path(out) / "config.json").read_text())
        saved = {k: v for k, v in data.items() if k in Args.__dataclass_fields__}
        saved.update(out=Path(saved["out"]), hidden_sizes=tuple(saved["hidden_sizes"]),
                     grid=ConditionGrid(**saved["grid"]))
        # Checked once the flags given have replaced the saved values, not before: a run saved with 1024 GPU envs
        # resumes on a CPU machine with --sim-backend physx_cpu --num-envs N (the saved config alone is refused here).
        default = unchecked(Args, saved)
    return parse_config(Args, argv, prog, help_, default=default)


def run(args: Args) -> int:
    result = train(args)
    ev = result["eval"]["all"] if result.get("eval") else {}
    print(files.dumps({"out": str(args.out), "global_step": result["global_step"], "sps": round(result["sps"], 1),
                      **{m: ev.get(m) for m in METRICS}}))
    return 0
