"""The noise schedule of the scene diffusion model: forward noising, the DDPM training loss, and DDIM
sampling steps that also return the Gaussian they sample from and the log-probability of a next state.

Written in the style of diffusers' schedulers (``set_timesteps`` then ``step`` returning a small
dataclass). Names map onto the symbols of DDPM / DDIM (Ho et al. 2020; Song et al. 2021) and of the
iARCS / DDPO papers:

=====================  =======================================================================
code                   paper
=====================  =======================================================================
``betas[t]``           beta_t, the variance added by forward step t (linear 1e-4 .. 0.02, T=1000)
``alphas[t]``          alpha_t = 1 - beta_t
``alphas_cumprod[t]``  alpha-bar_t = prod_{s<=t} alpha_s  (``a_t`` below)
``a_prev``             alpha-bar of the previous (less noisy) timestep t_prev of the DDIM grid,
                       or ``final_alpha_cumprod`` (= 1, i.e. clean data) when t_prev < 0
``sigma_t``            DDIM std: eta * sqrt((1-a_prev)/(1-a_t) * (1 - a_t/a_prev))
``pred_x0``            x0_hat = (x_t - sqrt(1-a_t) * eps) / sqrt(a_t)
``mean``               mu_t = sqrt(a_prev) * x0_hat + sqrt(1 - a_prev - sigma_t^2) * eps
``v``                  v = sqrt(a_t) * eps - sqrt(1-a_t) * x0 (Salimans & Ho 2022)
``snr(t)``             SNR_t = a_t / (1 - a_t)
=====================  =======================================================================

The model predicts epsilon (``prediction_type`` ``epsilon``, the default), x0 (``sample``) or v
(``v_prediction``): the training loss regresses that target, and :meth:`NoiseSchedule.predict_x0` and
:meth:`NoiseSchedule.predict_eps` convert the model's output, so DDIM steps work with any of them. One DDIM
step is the policy of the denoising MDP:
``pi(x_{t-1} | x_t) = N(mu_t, sigma_t^2 I)``; its log-probability is the MEAN of the per-element
Gaussian log-densities over a scene (as in DDPO), so that a PPO clip range of 1e-4 on the ratio is
meaningful. ``sigma_t`` is floored at ``min_std`` (1e-6) for the log-probability so that the last step
(where a_prev = 1 makes the DDIM variance exactly 0) never divides by a zero variance.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Callable

import torch

#: Floor of sigma_t in log-probabilities (and in sampling when eta > 0).
MIN_STD = 1e-6
_LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)
#: The model outputs :attr:`ScheduleConfig.prediction_type` knows (diffusers' names).
PREDICTION_TYPES = ("epsilon", "sample", "v_prediction")


def ddim_timesteps(num_steps: int, num_train_timesteps: int = 1000) -> torch.Tensor:
    """The DDIM grid, the one place it is computed: ``num_steps`` timesteps, evenly spaced and descending,
    ``t_k = k * (T // num_steps)`` ("leading" spacing: the last one is 0). Each step's previous timestep is
    ``t - T // num_steps`` (:func:`ddim_previous`; negative after the last step)."""
    if not 1 <= int(num_steps) <= num_train_timesteps:
        raise ValueError(f"the number of DDIM steps (num_steps) must be in 1..{num_train_timesteps}; got {num_steps}")
    return torch.arange(int(num_steps) - 1, -1, -1) * (num_train_timesteps // int(num_steps))


def ddim_previous(t: torch.Tensor | int, num_steps: int, num_train_timesteps: int = 1000) -> torch.Tensor:
    """t_prev of timestep ``t`` on the grid of :func:`ddim_timesteps`."""
    return torch.as_tensor(t).long() - num_train_timesteps // int(num_steps)


@dataclass
class ScheduleConfig:
    """Hyper-parameters of the noise schedule (saved in checkpoints)."""

    num_train_timesteps: int = 1000
    """T, the number of forward noising steps."""
    beta_start: float = 1e-4
    """beta_1 of the linear schedule."""
    beta_end: float = 0.02
    """beta_T of the linear schedule."""
    beta_schedule: str = "linear"
    """Only ``linear`` (the paper's)."""
    prediction_type: str = "epsilon"
    """What the denoiser outputs: ``epsilon`` (the added noise), ``sample`` (the clean x0) or ``v_prediction``
    (v = sqrt(a_t) eps - sqrt(1 - a_t) x0). Saved with a prior, so that it samples as it was trained."""
    clip_sample: bool = True
    """Clip x0_hat to [-clip_sample_range, clip_sample_range] in DDIM steps (features live in [-1, 1])."""
    clip_sample_range: float = 1.0
    """Bound for ``clip_sample``."""
    final_alpha_cumprod: float = 1.0
    """alpha-bar used for a previous timestep < 0 (1: the last step lands on clean data)."""


@dataclass
class DDIMStepOutput:
    """What :meth:`NoiseSchedule.step` returns.

    ``prev_sample`` is x_{t-1} (the given ``prev_sample`` if one was passed, else a draw from
    N(mean, std^2)); ``std`` has shape (B, 1, ..., 1) and is already floored at ``min_std``;
    ``log_prob`` (B,) is the mean over a scene's elements of log N(prev_sample; mean, std^2).
    """

    prev_sample: torch.Tensor
    pred_original_sample: torch.Tensor
    mean: torch.Tensor
    std: torch.Tensor
    log_prob: torch.Tensor


def gaussian_log_prob(x: torch.Tensor, mean: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
    """Per-scene MEAN (over every element but the batch dimension) of elementwise Gaussian log-densities.

    ``std`` must be positive (broadcastable to ``x``); returns shape (B,).
    """
    std = torch.as_tensor(std, dtype=x.dtype, device=x.device).expand_as(x)
    lp = -((x - mean) ** 2) / (2 * std**2) - torch.log(std) - _LOG_SQRT_2PI
    return lp.flatten(1).mean(1)


def standard_normal(shape, generator: torch.Generator | None = None, device=None,
                    dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """N(0, I) noise of ``shape`` on ``device``, drawn on the generator's own device and then moved: a seeded CPU
    generator gives the same noise whether the model runs on the CPU or a GPU (torch cannot draw from a CPU
    generator straight into GPU memory)."""
    where = generator.device if generator is not None else device
    x = torch.randn(shape, generator=generator, dtype=dtype, device=where)
    return x if device is None else x.to(device)


class NoiseSchedule:
    """Linear-beta DDPM schedule with epsilon (x0 or v) prediction and DDIM sampling steps.

    Usage (sampling)::

        sched = NoiseSchedule()
        sched.set_timesteps(20)
        x = torch.randn(shape, generator=g)
        for t in sched.timesteps:
            eps = model(x, t)
            x = sched.step(eps, t, x, eta=1.0, generator=g).prev_sample
    """

    def __init__(self, config: ScheduleConfig | None = None, **overrides):
        cfg = config or ScheduleConfig()
        if overrides:
            cfg = ScheduleConfig(**{**asdict(cfg), **overrides})
        if cfg.beta_schedule != "linear":
            raise ValueError(f"unsupported beta_schedule {cfg.beta_schedule!r}; only 'linear' is implemented")
        if cfg.prediction_type not in PREDICTION_TYPES:
            raise ValueError(f"unsupported prediction_type {cfg.prediction_type!r}; choose one of: "
                             f"{', '.join(PREDICTION_TYPES)}")
        self.config = cfg
        T = cfg.num_train_timesteps
        # computed in float64, stored in float32 (the model's dtype)
        betas = torch.linspace(cfg.beta_start, cfg.beta_end, T, dtype=torch.float64)  # beta_t
        alphas = 1.0 - betas  # alpha_t
        alphas_cumprod = torch.cumprod(alphas, 0)  # alpha-bar_t
        self.betas = betas.float()
        self.alphas = alphas.float()
        self.alphas_cumprod = alphas_cumprod.float()
        self.final_alpha_cumprod = float(cfg.final_alpha_cumprod)
        self.num_inference_steps = T
        self.timesteps = ddim_timesteps(T, T)

    @property
    def num_train_timesteps(self) -> int:
        return self.config.num_train_timesteps

    # --- forward process ----------------------------------------------------------------------------
    def _abar(self, t: torch.Tensor | int, like: torch.Tensor) -> torch.Tensor:
        """alpha-bar_t for (B,) or scalar timesteps, with alpha-bar = final_alpha_cumprod for t < 0,
        reshaped to broadcast against ``like`` (B, ...)."""
        t = torch.as_tensor(t).long()
        if self.alphas_cumprod.device != t.device:  # kept where the timesteps are: no copy back to the host
            self.alphas_cumprod = self.alphas_cumprod.to(t.device)
        ac = self.alphas_cumprod[t.clamp(min=0)]
        ac = torch.where(t >= 0, ac, torch.full_like(ac, self.final_alpha_cumprod))
        ac = ac.to(device=like.device, dtype=like.dtype)
        if ac.ndim == 0:
            return ac
        return ac.reshape(ac.shape + (1,) * (like.ndim - ac.ndim))

    def q_sample(self, x0: torch.Tensor, t: torch.Tensor | int, noise: torch.Tensor) -> torch.Tensor:
        """x_t = sqrt(alpha-bar_t) x_0 + sqrt(1 - alpha-bar_t) eps  (q(x_t | x_0))."""
        a = self._abar(t, x0)
        return a.sqrt() * x0 + (1 - a).sqrt() * noise

    add_noise = q_sample  # diffusers' name

    def sample_timesteps(self, batch_size: int, generator: torch.Generator | None = None,
                         device=None) -> torch.Tensor:
        """Uniform training timesteps in [0, T) on ``device``, drawn on the generator's device (see
        :func:`standard_normal`)."""
        where = generator.device if generator is not None else device
        t = torch.randint(0, self.num_train_timesteps, (batch_size,), generator=generator, device=where)
        return t if device is None else t.to(device)

    def snr(self, t: torch.Tensor) -> torch.Tensor:
        """SNR_t = alpha-bar_t / (1 - alpha-bar_t) of (B,) timesteps."""
        a = self._abar(t, t.float())
        return a / (1 - a)

    def min_snr_weights(self, t: torch.Tensor, gamma: float = 5.0) -> torch.Tensor:
        """Min-SNR-gamma weights (B,) (Hang et al. 2023) of the loss in this schedule's prediction type:
        min(SNR_t, gamma) / SNR_t for epsilon, min(SNR_t, gamma) for x0, min(SNR_t, gamma) / (SNR_t + 1) for v:
        all three are min(SNR_t, gamma) times the x0 error. They lower the weight of the low-noise steps, which
        the plain epsilon loss stresses, relative to the mid-noise ones."""
        snr = self.snr(t)
        clipped = snr.clamp(max=gamma)
        kind = self.config.prediction_type
        return clipped / snr if kind == "epsilon" else clipped if kind == "sample" else clipped / (snr + 1)

    def training_target(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor | int) -> torch.Tensor:
        """What the model learns to output for x_t = :meth:`q_sample` (x0, t, noise): eps, x0 or v."""
        kind = self.config.prediction_type
        if kind == "epsilon":
            return noise
        if kind == "sample":
            return x0
        a = self._abar(t, x0)
        return a.sqrt() * noise - (1 - a).sqrt() * x0

    def training_loss(self, model_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], x0: torch.Tensor,
                      generator: torch.Generator | None = None, t: torch.Tensor | None = None,
                      noise: torch.Tensor | None = None, reduction: str = "mean",
                      feature_weights: torch.Tensor | None = None,
                      x0_penalty: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
                      scene_weights: torch.Tensor | None = None) -> torch.Tensor:
        """The DDPM "simple" loss E_{t, eps} || target - f_theta(x_t, t) ||^2 (mean over elements), the target
        eps (the plain DDPM loss), x0 or v as ``prediction_type`` says (:meth:`training_target`).

        ``model_fn(x_t, t)`` returns the model's prediction. ``reduction="none"`` gives one loss per scene.
        ``feature_weights`` (one per feature, broadcast over the last dimension) reweights the squared error
        of each feature; None is the plain loss. ``scene_weights`` (B,) weigh each scene's loss (a timestep
        weighting such as :meth:`min_snr_weights`). ``x0_penalty(x0_hat, x0, t)`` (one value per scene) is an
        auxiliary loss on the clean scene the model predicts (:meth:`predict_x0`), added to the scene's loss
        (not weighted by ``scene_weights``).
        """
        b = x0.shape[0]
        if t is None:
            t = self.sample_timesteps(b, generator, device=x0.device)
        if noise is None:
            noise = standard_normal(x0.shape, generator, x0.device, x0.dtype)
        x_t = self.q_sample(x0, t, noise)
        out = model_fn(x_t, t)
        err = (out - self.training_target(x0, noise, t)) ** 2
        if feature_weights is not None:
            err = err * feature_weights
        per_scene = err.flatten(1).mean(1)
        if scene_weights is not None:
            per_scene = per_scene * scene_weights
        if x0_penalty is not None:
            per_scene = per_scene + x0_penalty(self.predict_x0(x_t, t, out), x0, t)
        return per_scene.mean() if reduction == "mean" else per_scene

    # --- DDIM ---------------------------------------------------------------------------------------
    def set_timesteps(self, num_inference_steps: int) -> torch.Tensor:
        """Choose the DDIM grid of :func:`ddim_timesteps` for ``num_inference_steps``; returns ``timesteps``."""
        self.timesteps = ddim_timesteps(num_inference_steps, self.num_train_timesteps)
        self.num_inference_steps = len(self.timesteps)
        return self.timesteps

    def previous_timestep(self, t: torch.Tensor | int) -> torch.Tensor:
        """t_prev on the current grid (negative after the last step)."""
        return ddim_previous(t, self.num_inference_steps, self.num_train_timesteps)

    def ddim_std(self, t, t_prev, eta: float, like: torch.Tensor) -> torch.Tensor:
        """Unfloored DDIM sigma_t = eta * sqrt((1-a_prev)/(1-a_t) * (1 - a_t/a_prev)), broadcastable."""
        a_t = self._abar(t, like)
        a_prev = self._abar(t_prev, like)
        var = (1 - a_prev) / (1 - a_t) * (1 - a_t / a_prev)
        return eta * var.clamp(min=0).sqrt()

    def predict_x0(self, x_t: torch.Tensor, timestep: torch.Tensor | int, model_output: torch.Tensor) -> torch.Tensor:
        """The clean scene the model predicts: for epsilon x0_hat = (x_t - sqrt(1 - alpha-bar_t) eps) /
        sqrt(alpha-bar_t); for x0 the output itself; for v sqrt(alpha-bar_t) x_t - sqrt(1 - alpha-bar_t) v."""
        kind = self.config.prediction_type
        if kind == "sample":
            return model_output
        a_t = self._abar(timestep, x_t)
        if kind == "epsilon":
            return (x_t - (1 - a_t).sqrt() * model_output) / a_t.sqrt()
        return a_t.sqrt() * x_t - (1 - a_t).sqrt() * model_output

    def predict_eps(self, x_t: torch.Tensor, timestep: torch.Tensor | int, model_output: torch.Tensor) -> torch.Tensor:
        """The noise the model predicts: for epsilon the output itself; for x0 (x_t - sqrt(alpha-bar_t) x0_hat) /
        sqrt(1 - alpha-bar_t); for v sqrt(1 - alpha-bar_t) x_t + sqrt(alpha-bar_t) v."""
        kind = self.config.prediction_type
        if kind == "epsilon":
            return model_output
        a_t = self._abar(timestep, x_t)
        if kind == "sample":
            return (x_t - a_t.sqrt() * model_output) / (1 - a_t).sqrt()
        return (1 - a_t).sqrt() * x_t + a_t.sqrt() * model_output

    def step(self, model_output: torch.Tensor, timestep: torch.Tensor | int, sample: torch.Tensor,
             eta: float = 1.0, generator: torch.Generator | None = None, prev_sample: torch.Tensor | None = None,
             prev_timestep: torch.Tensor | int | None = None, clip_sample: bool | None = None,
             min_std: float = MIN_STD, noise: torch.Tensor | None = None) -> DDIMStepOutput:
        """One DDIM step x_t -> x_{t_prev}, with the Gaussian it samples from and a log-probability.

        ``model_output`` is the model's prediction (eps_theta(x_t, t) for epsilon prediction); ``timestep`` a
        scalar or (B,) tensor; ``prev_sample``, if given, is the next state whose log-probability is wanted
        (nothing is sampled then). With eta = 0 the step is deterministic (``prev_sample = mean``); ``std`` is
        still floored at ``min_std`` so the log-probability is finite.
        """
        if prev_timestep is None:
            prev_timestep = self.previous_timestep(timestep)
        clip = self.config.clip_sample if clip_sample is None else clip_sample
        x_t = sample
        eps = self.predict_eps(x_t, timestep, model_output)
        a_prev = self._abar(prev_timestep, x_t)  # alpha-bar_{t_prev}, 1 when t_prev < 0
        pred_x0 = self.predict_x0(x_t, timestep, model_output)
        if clip:
            r = self.config.clip_sample_range
            pred_x0 = pred_x0.clamp(-r, r)
        # sigma_t^2 = eta^2 (1-a_prev)/(1-a_t) (1 - a_t/a_prev)
        sigma = self.ddim_std(timestep, prev_timestep, eta, x_t)
        # "direction pointing to x_t": sqrt(1 - a_prev - sigma_t^2) * eps
        direction = (1 - a_prev - sigma**2).clamp(min=0).sqrt() * eps
        mean = a_prev.sqrt() * pred_x0 + direction
        std = sigma.clamp(min=min_std)
        if std.ndim == 0:
            std = std.reshape((1,) * x_t.ndim)
        std = std.expand((x_t.shape[0],) + (1,) * (x_t.ndim - 1)).contiguous()
        if prev_sample is None:
            if eta > 0:
                if noise is None:
                    noise = standard_normal(x_t.shape, generator, x_t.device, x_t.dtype)
                prev_sample = mean + std * noise
            else:
                prev_sample = mean
        log_prob = gaussian_log_prob(prev_sample, mean, std)
        return DDIMStepOutput(prev_sample, pred_x0, mean, std, log_prob)

    # --- a whole rollout ----------------------------------------------------------------------------
    def sample(self, model_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], shape,
               num_steps: int = 20, eta: float = 1.0, generator: torch.Generator | None = None,
               x_T: torch.Tensor | None = None, device=None, dtype=torch.float32,
               return_trajectory: bool = False):
        """DDIM rollout from x_T ~ N(0, I). ``model_fn(x_t, t)`` returns the model's prediction (apply guidance
        inside it, see :func:`classifier_free_guidance`). Returns x_0, or ``(x_0, trajectory)`` where the trajectory
        is a dict of stacked ``states`` (S+1, B, ...), ``timesteps`` (S,), ``log_probs`` (S, B)."""
        self.set_timesteps(num_steps)
        x = x_T if x_T is not None else standard_normal(shape, generator, device, dtype)
        states, log_probs = [x], []
        for t in self.timesteps:
            tt = torch.full((x.shape[0],), int(t), dtype=torch.long, device=x.device)
            out = self.step(model_fn(x, tt), tt, x, eta=eta, generator=generator)
            x = out.prev_sample
            if return_trajectory:
                states.append(x)
                log_probs.append(out.log_prob)
        if not return_trajectory:
            return x
        return x, {"states": torch.stack(states), "timesteps": self.timesteps.clone(),
                   "log_probs": torch.stack(log_probs)}


def classifier_free_guidance(eps_cond: torch.Tensor, eps_uncond: torch.Tensor, scale: float) -> torch.Tensor:
    """eps = eps_uncond + w (eps_cond - eps_uncond); w = 1 is plain conditional sampling.

    The unconditional prediction is the denoiser's output with the floor condition dropped (its input
    points zeroed, as during training with condition dropout)."""
    return eps_uncond + scale * (eps_cond - eps_uncond)


def guided_model_fn(model: Callable[..., torch.Tensor], cond: torch.Tensor, guidance_scale: float = 1.0,
                    uncond: torch.Tensor | None = None) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """Wrap ``model(x_t, t, cond)`` into ``f(x_t, t)`` with optional classifier-free guidance.

    With ``guidance_scale != 1`` the conditional and unconditional (``uncond``, default zeros) passes run as
    one doubled batch."""
    if guidance_scale == 1.0:
        return lambda x, t: model(x, t, cond)
    unc = torch.zeros_like(cond) if uncond is None else uncond

    def fn(x, t):
        eps = model(torch.cat([x, x]), torch.cat([t, t]), torch.cat([cond, unc]))
        e_c, e_u = eps.chunk(2)
        return classifier_free_guidance(e_c, e_u, guidance_scale)

    return fn


__all__ = ["DDIMStepOutput", "MIN_STD", "NoiseSchedule", "PREDICTION_TYPES", "ScheduleConfig",
           "classifier_free_guidance", "gaussian_log_prob", "guided_model_fn", "standard_normal"]
