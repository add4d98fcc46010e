"""Pure loss and target functions shared by the continuous agents, each tested on exact numbers.

Shapes: B = batch, N = samples or atoms of the source distribution, M = atoms of the target
support, A = action dimensions, K = mixture components.
"""

from __future__ import annotations

import math

import torch
from torch.nn import functional as F


def bootstrap_values(
    reward: torch.Tensor,
    discount: torch.Tensor,
    bootstrap_gamma: float,
    next_values: torch.Tensor,
) -> torch.Tensor:
    """r + gamma^n d v for every value v (atom or sample) of the next state: (B, N) -> (B, N);
    ``bootstrap_gamma`` is gamma^n (``BatchSpec.bootstrap_gamma``)."""
    return reward[:, None] + bootstrap_gamma * discount[:, None] * next_values


def smoothed_target_action(
    next_action: torch.Tensor, sigma: float, clip: float, generator: torch.Generator
) -> torch.Tensor:
    """TD3's target policy smoothing (TD3+BC, ReBRAC): clip(a' + clip(sigma eps, -clip, clip),
    -1, 1) with eps ~ N(0, I) drawn from ``generator`` on the actions' device; (B, A) ->
    (B, A)."""
    eps = torch.randn(next_action.shape, generator=generator, device=next_action.device)
    return (next_action + (sigma * eps).clamp(-clip, clip)).clamp(-1.0, 1.0)


def categorical_projection(
    values: torch.Tensor, probs: torch.Tensor, atoms: torch.Tensor
) -> torch.Tensor:
    """Project a distribution with mass ``probs`` at ``values`` (B, N) onto ``atoms`` (M,).

    Mass at a value between two atoms is split between them linearly (C51's projection, Acme's
    ``l2_project``); values outside [atoms[0], atoms[-1]] are clipped onto the end atoms.
    Assumes evenly spaced atoms.
    """
    vmin, vmax = atoms[0], atoms[-1]
    delta = (vmax - vmin) / (atoms.shape[0] - 1)
    v = values.clamp(vmin, vmax)
    # (B, N, M) hat functions: weight of value i on atom j.
    w = (1.0 - (v[..., None] - atoms).abs() / delta).clamp(min=0.0)
    return (probs[..., None] * w).sum(-2)


def categorical_cross_entropy(logits: torch.Tensor, target_probs: torch.Tensor) -> torch.Tensor:
    """Per-row cross-entropy H(target, softmax(logits)): (B, M) -> (B,)."""
    return -(target_probs * F.log_softmax(logits, -1)).sum(-1)


def gaussian_log_prob(mean: torch.Tensor, std: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """log N(x; mean, diag(std^2)) summed over the last axis."""
    z = (x - mean) / std
    return (-0.5 * z * z - torch.log(std) - 0.5 * math.log(2 * math.pi)).sum(-1)


def mixture_log_prob(
    logits: torch.Tensor, mean: torch.Tensor, std: torch.Tensor, action: torch.Tensor
) -> torch.Tensor:
    """log sum_k softmax(logits)_k N(action; mean_k, std_k).

    Shapes (B, K), (B, K, A), (B, K, A), (B, A) -> (B,).
    """
    comp = gaussian_log_prob(mean, std, action.unsqueeze(-2))
    return torch.logsumexp(F.log_softmax(logits, -1) + comp, -1)


def vae_loss(
    recon: torch.Tensor,
    action: torch.Tensor,
    mean: torch.Tensor,
    std: torch.Tensor,
    kl_weight: float = 0.5,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """BCQ's VAE loss (Fujimoto et al. 2019): MSE + 0.5 KL(N(mean, std) || N(0, 1))."""
    recon_loss = F.mse_loss(recon, action)
    kl = -0.5 * (1 + torch.log(std.pow(2)) - mean.pow(2) - std.pow(2)).mean()
    return recon_loss + kl_weight * kl, {"vae/recon_loss": recon_loss, "vae/kl": kl}


def sample_kl(policy_log_prob: torch.Tensor, behaviour_log_prob: torch.Tensor) -> torch.Tensor:
    """BRAC's KL(pi || b) estimate from S samples a ~ pi: mean_s [log pi(a_s) - log b(a_s)].

    (S, B) -> (B,).
    """
    return (policy_log_prob - behaviour_log_prob).mean(0)


def tanh_gaussian_log_prob(
    mean: torch.Tensor, std: torch.Tensor, pre_tanh: torch.Tensor
) -> torch.Tensor:
    """log density of tanh(u), u ~ N(mean, std), at u = ``pre_tanh`` (change of variables)."""
    log_det = 2.0 * (math.log(2.0) - pre_tanh - F.softplus(-2.0 * pre_tanh))
    return gaussian_log_prob(mean, std, pre_tanh) - log_det.sum(-1)


def abm_weights(
    advantage: torch.Tensor, kind: str = "binary", temperature: float = 1.0
) -> torch.Tensor:
    """ABM's prior weights f(A) (Siegel et al. 2020): the step 1[A >= 0] or exp(A / temperature).

    The exponential variant is normalised to mean 1 over the batch (AWR-style) so the learning
    rate means the same thing for both.
    """
    if kind == "binary":
        return (advantage >= 0).to(advantage.dtype)
    if kind == "exp":
        w = torch.softmax(advantage / temperature, 0) * advantage.shape[0]
        return w
    raise ValueError(f"abm weight kind must be 'binary' or 'exp', got {kind!r}")


def mpo_e_step(
    q_values: torch.Tensor, temperature: torch.Tensor, epsilon: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """MPO's non-parametric E-step over N sampled actions per state: q_values (N, B).

    Returns the weights softmax_n(Q / eta) (N, B), detached, and the temperature dual
    g(eta) = eta * epsilon + eta * mean_b log mean_n exp(Q_nb / eta).
    """
    q = q_values.detach()
    weights = torch.softmax(q / temperature, 0).detach()
    n = q.shape[0]
    dual = (
        temperature * epsilon
        + temperature * (torch.logsumexp(q / temperature, 0) - math.log(n)).mean()
    )
    return weights, dual


def gaussian_kl(
    mean_p: torch.Tensor, std_p: torch.Tensor, mean_q: torch.Tensor, std_q: torch.Tensor
) -> torch.Tensor:
    """KL(N(mean_p, std_p) || N(mean_q, std_q)) of diagonal Gaussians, summed over the last axis."""
    var_p, var_q = std_p.pow(2), std_q.pow(2)
    kl = torch.log(std_q / std_p) + (var_p + (mean_p - mean_q).pow(2)) / (2 * var_q) - 0.5
    return kl.sum(-1)
