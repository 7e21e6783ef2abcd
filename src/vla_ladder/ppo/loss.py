"""The PPO maths: generalised advantage estimates and the clipped surrogate objective (CleanRL's)."""

from __future__ import annotations

import torch


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
    """The clipped PPO objective (to minimise) and its parts, for one minibatch (0-d tensors on its device)."""
    logratio = newlogprob - oldlogprob
    ratio = logratio.exp()
    if norm_adv:
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    pg_loss = torch.max(-advantages * ratio, -advantages * torch.clamp(ratio, 1 - clip_coef, 1 + clip_coef)).mean()
    v_loss = 0.5 * ((newvalue - returns) ** 2).mean()
    entropy_loss = entropy.mean()
    loss = pg_loss - ent_coef * entropy_loss + vf_coef * v_loss
    # Tensors, not floats: reading one on the host (.item()) waits for the GPU, and five a minibatch did so hundreds
    # of times an update; train.py reads them together once an update.
    with torch.no_grad():  # http://joschu.net/blog/kl-approx.html
        stats = dict(pg_loss=pg_loss.detach(), v_loss=v_loss.detach(), entropy=entropy_loss.detach(),
                     approx_kl=((ratio - 1) - logratio).mean(),
                     clipfrac=((ratio - 1.0).abs() > clip_coef).float().mean())
    return loss, stats
