"""The RL stage's objective as pure tensor functions (GRPO: Shao et al. 2024, "DeepSeekMath", section 4.1).

- group-relative advantages: each rollout's reward minus its group's mean, over the group's standard deviation
  (Bessel-corrected, as `torch.std`) plus `eps`; a group whose rewards are all equal gets zero advantages;
- the PPO clipped surrogate on the log-probabilities of the taken action tokens;
- the k3 estimate of KL(policy || reference): `exp(ref - logp) - (ref - logp) - 1` (Schulman 2020), >= 0 per token,
  unbiased, what GRPO adds to the loss.
"""

from __future__ import annotations

import torch

ADVANTAGE_EPS = 1e-4  # keeps a group of nearly equal rewards from dividing by a std of about 0


def group_advantages(rewards: torch.Tensor, eps: float = ADVANTAGE_EPS) -> torch.Tensor:
    """(N, G) rewards of N groups of G rollouts -> (N, G) advantages `(r - mean) / (std + eps)`.

    `std` is the Bessel-corrected standard deviation of the group (divides by G - 1): rewards [1, 0, 0, 1] give
    mean 0.5, std sqrt(1/3) and advantages +-0.866. A group with zero std gets exactly zero advantages.
    """
    if rewards.ndim != 2 or rewards.shape[1] < 2:
        raise ValueError(f"rewards must be (groups, G >= 2), got {tuple(rewards.shape)}")
    rewards = rewards.double()
    mean = rewards.mean(dim=1, keepdim=True)  # (N, 1)
    std = rewards.std(dim=1, keepdim=True)  # (N, 1), unbiased
    return torch.where(std > 0, (rewards - mean) / (std + eps), torch.zeros_like(rewards)).float()


def k3_kl(logp: torch.Tensor, ref_logp: torch.Tensor) -> torch.Tensor:
    """Per-token k3 estimate of KL(policy || reference) from the taken tokens' log-probs (same shape)."""
    log_ratio = ref_logp - logp
    return torch.exp(log_ratio) - log_ratio - 1.0


def clipped_policy_loss(
    logp: torch.Tensor, old_logp: torch.Tensor, advantages: torch.Tensor, clip_epsilon: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-token PPO loss `-min(ratio * A, clip(ratio, 1 - eps, 1 + eps) * A)` with `ratio = exp(logp - old)`,
    and whether the clipped term was the one taken (the token's gradient is zero there).

    Args:
        logp: (n,) log-probs of the taken tokens under the policy being trained (with gradient).
        old_logp: (n,) the same under the policy that sampled them (the update's start), no gradient.
        advantages: (n,) the advantage of each token's rollout.
    """
    ratio = torch.exp(logp - old_logp)
    unclipped = ratio * advantages
    clipped = ratio.clamp(1.0 - clip_epsilon, 1.0 + clip_epsilon) * advantages
    return -torch.minimum(unclipped, clipped), clipped < unclipped


def rl_loss(
    logp: torch.Tensor,
    old_logp: torch.Tensor,
    ref_logp: torch.Tensor,
    advantages: torch.Tensor,
    clip_epsilon: float,
    kl_coef: float,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Sum over the tokens of `clipped_policy_loss + kl_coef * k3_kl` (the caller divides by its token count),
    and the sums of its parts (`pg_loss`, `kl`, `clipped`) for the logs."""
    policy, clipped = clipped_policy_loss(logp, old_logp, advantages, clip_epsilon)
    kl = k3_kl(logp, ref_logp)
    total = (policy + kl_coef * kl).sum()
    return total, {"pg_loss": policy.detach().sum(), "kl": kl.detach().sum(), "clipped": clipped.sum()}


def action_log_probs(
    logits: torch.Tensor, targets: torch.Tensor, action_ids: torch.Tensor, temperature: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The `discrete` head's policy at `temperature` (what the session samples from): (n,) log-probs of the
    taken actions and (n,) entropies of softmax(logits[:, action_ids] / temperature).

    Args:
        logits: (n, V) the LM logits at the positions that predict the n action tokens (`forward`'s outputs).
        targets: (n,) the taken actions' token ids (each one of `action_ids`).
        action_ids: (A,) the token id of each action, in action order.
    """
    matches = targets[:, None] == action_ids[None, :]  # (n, A)
    if not bool(matches.any(dim=1).all()):
        raise ValueError("an action target is not one of the discrete head's action tokens")
    log_probs = torch.log_softmax(logits[:, action_ids].float() / temperature, dim=-1)  # (n, A)
    taken = log_probs.gather(1, matches.float().argmax(dim=1, keepdim=True))[:, 0]  # (n,)
    entropy = -(log_probs.exp() * log_probs).sum(dim=-1)  # (n,)
    return taken, entropy
