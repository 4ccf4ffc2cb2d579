"""DDPO (Black et al., "Training Diffusion Models with Reinforcement Learning") on the denoising MDP,
with the Stable-Baselines surface: ``DDPO(policy, env, **hyperparameters).learn(total_timesteps)``,
``save``/``load``, ``predict`` and callbacks.

One epoch = ``num_batches_per_epoch`` rollout batches of B scenes (the vector env's ``num_envs``), each a
full DDIM chain of S steps, then ``num_inner_epochs`` passes of updates over the stored transitions.
Symbols: ``r(x_0)`` terminal reward; advantages ``A = clip((r - mean_f) / std_f, -c, c)`` normalised per
floor plan f (DDPO's per-prompt statistics) or per batch; importance ratio
``rho = pi_theta(x_{t-1}|x_t) / pi_old(x_{t-1}|x_t)`` with mean-reduced log-probabilities; DDPO-IS loss
``mean(max(-A rho, -A clip(rho, 1-eps, 1+eps)))`` computed by TorchRL's ``ClipPPOLoss`` (no critic, no
entropy bonus). :class:`DDPOSF` swaps in the score-function loss ``-mean(A log pi_theta)``.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from iarcs_env.env import evaluate_reward
from iarcs_env.geometry import OUT_OF_BOUND_SHRINK
from iarcs_env.schedule import ddim_previous

from . import distributed
from .callbacks import HIGHER_IS_BETTER, LOWER_IS_BETTER, as_callback, render_grid_tensor
from .policy import DiffusionPolicy


@dataclass
class DDPOConfig:
    """DDPO hyper-parameters (names after kvablack/ddpo-pytorch where they exist)."""

    samples_per_floor: int = 4
    """Scenes per floor plan in a rollout batch; advantages are normalised within each floor's group."""
    num_batches_per_epoch: int = 1
    """Rollout batches of B = num_envs scenes per epoch."""
    num_inner_epochs: int = 1
    """Passes over the epoch's transitions."""
    minibatch_size: int = 8
    """Scenes per optimiser step (all their sampled timesteps go into that step)."""
    timestep_fraction: float = 1.0
    """Fraction of each chain's S timesteps trained on (a random subset per scene)."""
    learning_rate: float = 3e-4
    """Adam learning rate of the LoRA parameters."""
    adam_beta1: float = 0.9
    adam_beta2: float = 0.999
    adam_weight_decay: float = 1e-4
    adam_epsilon: float = 1e-8
    max_grad_norm: float = 1.0
    """Gradient-norm clip."""
    clip_range: float = 1e-4
    """PPO/DDPO clip range eps of the importance ratio (meaningful with mean-reduced log-probs)."""
    adv_clip_max: float = 5.0
    """Advantages are clipped to +-adv_clip_max."""
    per_floor_advantages: bool = True
    """Normalise advantages per floor plan (False: per batch)."""
    per_term_advantages: bool = False
    """Standardise each term of a composite reward before the weighted sum, so that every term carries its
    weight's share of the signal whatever the spread of its values (e.g. a task reward in [0, 1] next to
    universal rewards that vary much more)."""
    x0_baseline: bool = False
    """Per-step advantages with the reward of the clean scene the policy predicts at each step as a baseline:
    A_t = r(x_0) - beta_t r(x0_hat(x_t)), beta_t the least-squares fit over the batch (deviations from each
    floor's mean), then standardised per step. The baseline is a function of the state x_t only, so the
    gradient stays unbiased; it takes out of step t's credit what the chain had already decided at x_t
    (which objects the room holds, once they have settled), which is most of a scene's reward spread."""
    gae_lambda: float = 1.0
    """With ``x0_baseline``: lambda < 1 takes r(x0_hat(x_t)) as the value V(x_t) of a critic-free GAE(lambda)
    (gamma = 1, V(x_0) = r(x_0)): A_t = sum_k lambda^(k-t) delta_k with delta_k = V(x_{k-1}) - V(x_k), each
    step's change of the predicted scene's reward, centred and standardised per step. lambda = 1 is the
    fitted baseline above; lambda = 0 credits a step only with what it changed itself (least variance,
    greedy: biased towards improvements the following steps keep)."""
    # the fields marked ``physics-gradient`` only below are also descent-imitation's (agents/descent_imitation.py)
    gradient_steps: int = 4
    """``physics-gradient`` only (agents/physics_gradient.py): the last k stochastic steps whose x0_hat gets the
    gradient of the physics penalty (and of a stage-2 task reward)."""
    overlap_weight: float = 1.0
    """``physics-gradient`` only: the weight of the ground objects' overlap volume (m^3)."""
    overlap_measure: str = "volume"
    """``physics-gradient`` only: what a pair of overlapping ground objects is charged: ``volume`` (m^3) or
    ``depth``, the penetration (m) along the axis that separates them soonest, plus 0.02 m. Volume's pull fades
    with the overlap (two corners touching feel almost none); depth pushes every overlapping pair out alike, as
    Col_obj counts them. A pair of the collision reward's ``contact`` classes is then charged only through
    ``contact_gap_weight``."""
    contact_gap_weight: float = 0.0
    """``physics-gradient`` only: > 0 charges a pair of the collision reward's ``contact`` classes closer than 0.6 m
    this weight times its distance (m) from a ``contact_gap`` gap, in place of its overlap (a seat near its table
    is drawn to it without entering it)."""
    contact_gap: float = 0.05
    """``physics-gradient`` only: the gap (m) between their bounds that ``contact_gap_weight`` draws a contact pair
    to; wider than the sampler's last steps move an object, or the pair ends up touching (Col_obj counts it)."""
    contact_gap_walkway: bool = False
    """``physics-gradient`` only: ``contact_gap_weight`` draws a pair out only where standing the drawn object (the
    first class of its ``contact`` pair: the seat) at ``contact_gap`` narrows no passage below R_reach's agent (0.6
    m wide); elsewhere the pair is left as it is. A chair pulled out towards a wall or a cabinet closes the walkway
    behind it (``iarcs_env.clearance.room_to_pull``)."""
    passage_weight: float = 0.0
    """``physics-gradient`` only: charges each gap g between two ground objects' bounds (not a seat with a table or
    another seat) and between an object and a wall this weight times min(g - 0.05, 0.6 - g) while 0.05 < g < 0.6 m:
    a gap too narrow for R_reach's agent is closed or opened to its width, whichever is nearer
    (:func:`agents.physics_gradient.narrow_passages`). A rule on each pair's own gap, where ``reach_weight`` looks at
    the whole room's paths."""
    uncharged_pairs: list | None = None
    """``physics-gradient`` only: class pairs (names or groups, e.g. ``[[seat, desk]]``) whose overlap is not
    charged: a chair half under its desk, the data's own contact (charged, chairs left their desks more often:
    ``research/seat_desk_pulls.py``)."""
    reach_weight: float = 0.0
    """``physics-gradient`` only: > 0 charges every ground object out of R_reach's reach this weight times how much
    its widest free path is too narrow (m: the agent radius, 0.3 m, less the path's clearance at its narrowest;
    :func:`iarcs_env.clearance.reach_clearance`): the objects that close a walkway move to open it."""
    best_of_floor_weight: float = 0.0
    """``physics-gradient`` only: > 0 adds this weight times the mean square of the clean scene x0_hat that the
    adapter predicts at the steps of ``best_of_floor_t`` of each floor's best rollout (highest reward of its
    ``samples_per_floor``) against the room that rollout ended in (its objects' adapted features): the choices a
    room makes at mid noise, which the late steps' gradient does not reach (which wall the bed faces), drawn
    towards the group's best (reward-ranked fine-tuning, RAFT, on the policy's own states)."""
    best_of_floor_t: list = field(default_factory=lambda: [250, 450])
    """``physics-gradient`` only: the range of timesteps [low, high] whose states ``best_of_floor_weight`` uses."""
    descent_steps: int = 300
    """``descent-imitation`` only (agents/descent_imitation.py): the Adam steps that move each rollout's rooms down
    the physics penalty before the adapter learns them."""
    out_of_bound_weight: float = 1.0
    """``physics-gradient`` only: the weight of the out-of-bound area (m^2) next to the overlap volume (m^3)."""
    out_of_bound_shrink: float = OUT_OF_BOUND_SHRINK
    """``physics-gradient`` only: footprints are shrunk by this much (m) per side before their area outside the
    floor is penalised: R_out's own 0.05 m by default; 0 keeps whole footprints inside, 0.05 m short of R_out's
    threshold."""
    kl_coef: float = 0.0
    """Weight of a KL penalty to the policy the adapter starts from (its reference adapter, e.g. stage 1 for a
    partial stage-2 adapter; else the prior, adapters disabled), against diversity collapse and drift."""
    seed: int = 0
    """Seeds floor choice, the policy's noise and the environment."""

    @classmethod
    def from_dict(cls, values: dict) -> "DDPOConfig":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown DDPO hyper-parameter(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
        return cls(**values)


def x0_baseline_fit(rewards: torch.Tensor, values: torch.Tensor, groups: list[torch.Tensor]):
    """The ``x0_baseline`` fit. ``rewards`` (B,) r(x_0); ``values`` (B, S) r(x0_hat(x_t)) of each step;
    ``groups`` boolean masks whose means are removed first (floor plans). Returns the residuals
    r - beta_t v_t (B, S), beta (S,) and the share of the rewards' within-group variance each step's
    baseline explains (S,)."""
    r, v = rewards.double(), values.double()
    rd, vd = r.clone(), v.clone()
    for m in groups:
        rd[m], vd[m] = r[m] - r[m].mean(), v[m] - v[m].mean(0)
    beta = (vd * rd[:, None]).sum(0) / (vd**2).sum(0).clamp(min=1e-12)
    residual = rd[:, None] - beta * vd
    return residual, beta, 1 - residual.var(0) / rd.var().clamp(min=1e-12)


def gae_advantages(rewards: torch.Tensor, values: torch.Tensor, lam: float) -> torch.Tensor:
    """GAE(lambda) with gamma = 1 over a chain (B, S): ``values`` V(x_t) of the state before each step, the
    terminal reward ``rewards`` (B,) as the value after the last. Returns A (B, S), centred per step (a
    constant per step is a baseline)."""
    v = torch.cat([values.double(), rewards.double()[:, None]], 1)
    delta = v[:, 1:] - v[:, :-1]
    advantage = torch.zeros_like(delta)
    running = torch.zeros_like(delta[:, 0])
    for s in reversed(range(delta.shape[1])):
        running = delta[:, s] + lam * running
        advantage[:, s] = running
    return advantage - advantage.mean(0)


def _stack_terms(terms: dict) -> torch.Tensor:
    """(B, K) float32 tensor of a composite reward's per-term values ``{name: (B,)}``, in the terms' order."""
    return torch.from_numpy(np.stack([np.asarray(v, dtype=np.float32) for v in terms.values()], -1))


def _per_step_standardised(values: torch.Tensor) -> torch.Tensor:
    return values / (values.std(0, unbiased=False) + 1e-8)


class DDPO:
    """DDPO-IS: importance-sampled, clipped policy gradient on the terminal reward.

    Args:
        policy: the :class:`DiffusionPolicy` (its active LoRA adapter is trained).
        env: the batched denoising environment (``gym.make_vec(..., vectorization_mode="vector_entry_point")``
            or :class:`iarcs_env.env.DenoisingVectorEnv`).
        tensorboard_log: folder for TensorBoard event files (None: no logging).
        config / **hyperparameters: :class:`DDPOConfig` fields.
    """

    name = "DDPO-IS"

    def __init__(self, policy: DiffusionPolicy, env, config: DDPOConfig | None = None,
                 tensorboard_log: str | Path | None = None, verbose: int = 1, **hyperparameters):
        cfg = config or DDPOConfig()
        if hyperparameters:
            cfg = DDPOConfig.from_dict({**asdict(cfg), **hyperparameters})
        self.config = cfg
        self.policy = policy
        self.env = env
        self.venv = env.unwrapped
        self.verbose = verbose
        b = self.venv.num_envs
        if b % cfg.samples_per_floor:
            raise ValueError(f"the env's num_envs ({b}) must be a multiple of samples_per_floor ({cfg.samples_per_floor})")
        if self.venv.num_steps != policy.num_steps:
            raise ValueError(f"the env runs {self.venv.num_steps} DDIM steps but the policy {policy.num_steps}; "
                             "make them equal")
        if self.venv.stats.to_json() != policy.prior.stats.to_json():
            raise ValueError("the env scales features with other dataset statistics than the prior; "
                             "create the env with stats=prior.stats")
        if not 0.0 <= cfg.gae_lambda <= 1.0 or (cfg.gae_lambda < 1 and not cfg.x0_baseline):
            raise ValueError(f"gae_lambda must be in [0, 1] and needs x0_baseline: true (its values are the predicted "
                             f"scenes' rewards); got gae_lambda={cfg.gae_lambda}, x0_baseline={cfg.x0_baseline}")
        if cfg.per_term_advantages and not isinstance(getattr(self.venv.reward_fn, "weights", None), dict):
            raise ValueError("per_term_advantages needs a composite reward (rewards.composite.CompositeReward) whose "
                             "terms and weights it can standardise")
        self.optimizer = torch.optim.AdamW(policy.trainable_parameters(), lr=cfg.learning_rate,
                                           betas=(cfg.adam_beta1, cfg.adam_beta2),
                                           weight_decay=cfg.adam_weight_decay, eps=cfg.adam_epsilon)
        self.loss_module = self._make_loss()
        self._seed = distributed.rank_seed(cfg.seed)  # cfg.seed in a one-process run
        self.rng = np.random.default_rng(self._seed)
        self.generator = torch.Generator().manual_seed(self._seed)
        self.epoch = 0
        self.num_timesteps = 0
        self._env_seeded = False
        self.tensorboard_log = Path(tensorboard_log) if tensorboard_log and distributed.is_main() else None
        distributed.broadcast_parameters(policy.trainable_parameters())  # every rank starts from rank 0's adapter
        self._writer = None

    # --- loss ------------------------------------------------------------------------------------------
    def _make_loss(self):
        from torchrl.objectives import ClipPPOLoss

        loss = ClipPPOLoss(actor_network=self.policy.actor(), critic_network=None, clip_epsilon=self.config.clip_range,
                           entropy_bonus=False, normalize_advantage=False, functional=False)
        loss.set_keys(sample_log_prob="sample_log_prob", action="action", advantage="advantage")
        return loss

    def policy_loss(self, batch: TensorDict) -> tuple[torch.Tensor, dict[str, float]]:
        """DDPO-IS loss of a flat batch of transitions (x_t, t, floor, action, sample_log_prob, advantage)."""
        out = self.loss_module(batch)
        loss = out["loss_objective"]
        info = {"clip_fraction": float(out["clip_fraction"]), "approx_kl": float(out["kl_approx"])}
        return loss, info

    @property
    def device(self) -> torch.device:
        """Where the policy's weights are (``policy.to(device)`` moves them; rollouts stay on the CPU)."""
        return self.policy.prior.device

    # --- rollouts --------------------------------------------------------------------------------------
    def collect_rollouts(self) -> TensorDict:
        """One batch of B full chains: a TensorDict [B, S] of transitions, plus per-scene ``reward``,
        ``terms`` and ``floor_index`` (non-batched entries in ``td["meta"]``-style keys)."""
        cfg, venv = self.config, self.venv
        n_floors = venv.num_envs // cfg.samples_per_floor
        picked = self.rng.choice(len(venv.floors), n_floors, replace=n_floors > len(venv.floors))
        floor_idx = np.repeat(picked, cfg.samples_per_floor)
        seed = None if self._env_seeded else self._seed
        self._env_seeded = True
        obs, _ = self.env.reset(seed=seed, options={"floor_indices": floor_idx})
        # an adapter with required objects: its rooms' classes, one list per floor plan (so that the advantages
        # within a floor's group compare arrangements of the same objects), given at every step and in the scene scored
        classes = self.policy.required_classes([venv.floors[i] for i in picked], self.generator)
        prior = self.policy.prior
        if classes is not None:
            classes = classes.repeat_interleave(cfg.samples_per_floor, 0)
        steps, predicted = [], []  # predicted: x0_hat(x_t) of each step, scored only with x0_baseline
        on = self.device  # rollouts are stored on the CPU; the policy runs where its weights are
        for k in range(venv.num_steps):
            x_t = torch.from_numpy(obs["x_t"])
            t = torch.from_numpy(obs["t"])
            floor = torch.from_numpy(obs["floor"])
            if classes is not None:
                x_t = prior.with_classes(x_t, t.reshape(-1), classes, self.generator)
            action, log_prob, *x0_hat = (v.cpu() for v in self.policy.act(
                x_t.to(on), t.to(on), floor.to(on), generator=self.generator, return_x0=cfg.x0_baseline,
                classes=None if classes is None else classes.to(on)))
            steps.append({"x_t": x_t, "t": t, "floor": floor, "action": action, "sample_log_prob": log_prob}
                         | ({} if classes is None else {"classes": classes}))
            predicted += [self._given(x, classes) for x in x0_hat]
            last = k == venv.num_steps - 1
            obs, reward, terminated, _, info = self.env.step((self._given(action, classes) if last else action).numpy())
        if not terminated.all():
            raise RuntimeError("the environment did not terminate after num_steps steps")
        td = TensorDict({k: torch.stack([s[k] for s in steps], 1) for k in steps[0]}, batch_size=[venv.num_envs, venv.num_steps])
        td["reward"] = torch.as_tensor(reward, dtype=torch.float32)[:, None].expand(-1, venv.num_steps)
        td["floor_index"] = torch.as_tensor(floor_idx)[:, None].expand(-1, venv.num_steps)
        self._last_terms = info.get("terms", {})
        if self._last_terms:
            td["terms"] = _stack_terms(self._last_terms)[:, None].expand(-1, venv.num_steps, -1)
        if predicted:  # r(x0_hat(x_t)) of every step (and its terms), on the episode's floors (not yet reset)
            scored = [evaluate_reward(venv.reward_fn, venv.decode(x.numpy())) for x in predicted]
            td["reward_x0_hat"] = torch.as_tensor(np.stack([total for total, _ in scored], 1), dtype=torch.float32)
            if self._last_terms:
                td["terms_x0_hat"] = torch.stack([_stack_terms(terms) for _, terms in scored], 1)
        self._last_scene = info.get("scene")
        self.num_timesteps += venv.num_envs * venv.num_steps
        return td

    def _given(self, x: torch.Tensor, classes: torch.Tensor | None) -> torch.Tensor:
        """Clean scene features ``x`` with the rooms' given classes (as they are without)."""
        if classes is None:
            return x
        return self.policy.prior.with_clean_classes(x, classes)

    def compute_advantages(self, rewards: torch.Tensor, floor_index: torch.Tensor,
                           terms: torch.Tensor | None = None, x0_values: torch.Tensor | None = None,
                           x0_terms: torch.Tensor | None = None) -> torch.Tensor:
        """A = (r - mean) / (std + 1e-8) per floor plan (or per batch), clipped to +-adv_clip_max.

        With ``per_term_advantages`` and the composite's per-term values ``terms`` (B, K), r is replaced by
        ``sum_k w_k z_k`` where z_k is term k standardised the same way. With ``x0_baseline`` and the rewards
        of each step's x0_hat ``x0_values`` (B, S) (and their terms ``x0_terms`` (B, S, K) for
        ``per_term_advantages``) the result is per step, (B, S) (:meth:`_x0_advantages`). Under ``torchrun``
        the statistics are those of every rank's scenes; the result is this rank's part."""
        rewards, floor_index = distributed.all_gather(rewards), distributed.all_gather(floor_index)
        terms = distributed.all_gather(terms) if terms is not None else None
        c = self.config.adv_clip_max
        if self.config.x0_baseline and x0_values is not None:
            x0_terms = distributed.all_gather(x0_terms) if x0_terms is not None else None
            advantage = self._x0_advantages(rewards, floor_index, distributed.all_gather(x0_values), terms, x0_terms)
            return distributed.local_part(advantage.clamp(-c, c).float())
        if self.config.per_term_advantages and terms is not None:
            weights = torch.tensor(list(self.venv.reward_fn.weights.values()), dtype=torch.float64)
            z = torch.stack([self._standardise(terms[:, k], floor_index) for k in range(terms.shape[1])], 1)
            rewards = (z * weights).sum(1)
        return distributed.local_part(self._standardise(rewards, floor_index).clamp(-c, c).float())

    def set_advantages(self, rollout: TensorDict) -> None:
        """Write ``rollout["advantage"]`` [B, S, 1] from the rollout's rewards (:meth:`compute_advantages`): one
        per scene shared by its steps, or one per step with ``x0_baseline``."""
        terms = rollout["terms"][:, 0] if "terms" in rollout.keys() else None
        advantage = self.compute_advantages(rollout["reward"][:, 0], rollout["floor_index"][:, 0], terms,
                                            rollout.get("reward_x0_hat", None), rollout.get("terms_x0_hat", None))
        if advantage.ndim == 1:
            advantage = advantage[:, None].expand(-1, rollout.batch_size[1])
        rollout["advantage"] = advantage[..., None].clone()

    def _groups(self, floor_index: torch.Tensor) -> list[torch.Tensor]:
        """Boolean masks of the advantage groups: one per floor plan, or the whole batch."""
        if not self.config.per_floor_advantages:
            return [torch.ones_like(floor_index, dtype=torch.bool)]
        return [floor_index == g for g in floor_index.unique()]

    def _standardise(self, values: torch.Tensor, floor_index: torch.Tensor) -> torch.Tensor:
        r = values.double()
        out = torch.zeros_like(r)
        for m in self._groups(floor_index):
            sel = r[m]
            std = sel.std(unbiased=False) if sel.numel() > 1 else sel.new_tensor(0.0)
            out[m] = (sel - sel.mean()) / (std + 1e-8)
        return out

    def _x0_advantages(self, rewards, floor_index, values, terms=None, term_values=None) -> torch.Tensor:
        """(B, S) advantages of ``x0_baseline``: r - beta_t r(x0_hat(x_t)) standardised per step; with
        ``per_term_advantages``, sum_k w_k z_k,t with z_k,t term k's residual standardised per step, standardised
        again. With ``gae_lambda`` < 1, :func:`gae_advantages` takes the fitted residual's place. Logs
        ``x0_baseline_r2``, the share of the total reward's within-group variance the baseline
        explains, averaged over the steps."""
        groups = self._groups(floor_index)
        residual, _, r2 = x0_baseline_fit(rewards, values, groups)
        self._x0_r2 = float(r2.mean())
        lam = self.config.gae_lambda

        def advantage(r, v):
            return x0_baseline_fit(r, v, groups)[0] if lam >= 1 else gae_advantages(r, v, lam)

        if self.config.per_term_advantages and terms is not None and term_values is not None:
            weights = self.venv.reward_fn.weights.values()
            return _per_step_standardised(sum(w * _per_step_standardised(advantage(terms[:, k], term_values[..., k]))
                                              for k, w in enumerate(weights)))
        return _per_step_standardised(residual if lam >= 1 else advantage(rewards, values))

    # --- updates ---------------------------------------------------------------------------------------
    def train(self, rollout: TensorDict) -> dict[str, float]:
        """``num_inner_epochs`` passes of minibatch updates over a rollout [B', S]."""
        cfg = self.config
        b = rollout.batch_size[0]
        steps = self.stochastic_steps()
        k = max(1, int(round(cfg.timestep_fraction * len(steps))))
        infos = []
        self.policy.model.eval()
        self.loss_module.to(self.device)  # its clip-range buffer follows the policy (e.g. moved after __init__)
        for _ in range(cfg.num_inner_epochs):
            perm = torch.randperm(b, generator=self.generator)
            for start in range(0, b, cfg.minibatch_size):
                rows = perm[start:start + cfg.minibatch_size]
                # a random subset of each scene's timesteps (all of them when timestep_fraction = 1)
                cols = torch.stack([steps[torch.randperm(len(steps), generator=self.generator)[:k]] for _ in rows])
                mb = rollout[rows[:, None], cols].reshape(-1).to(self.device)
                loss, info = self.policy_loss(mb)
                if cfg.kl_coef > 0:
                    kl = self.kl_to_base(mb)
                    loss = loss + cfg.kl_coef * kl
                    info["kl_to_base"] = float(kl)
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                distributed.average_gradients(self.policy.trainable_parameters())
                info["grad_norm"] = float(torch.nn.utils.clip_grad_norm_(self.policy.trainable_parameters(),
                                                                         cfg.max_grad_norm))
                self.optimizer.step()
                info["loss"] = loss.item()
                infos.append(info)
        return {key: float(np.mean([i[key] for i in infos])) for key in infos[0]}

    def stochastic_steps(self) -> torch.Tensor:
        """Indices of the chain's steps that sample. With eta = 1 the DDIM step onto x_0 (previous timestep
        < 0, alpha-bar = 1) has sigma = 0: its action is deterministic, its log-probability only exists
        through the 1e-6 floor, and its ratio gradient ((a - mu) / sigma^2) would swamp every other step's.
        It carries no policy-gradient signal, so it is left out of the updates."""
        t = torch.as_tensor(self.venv.timesteps)
        t_prev = ddim_previous(t, self.venv.num_steps, self.policy.schedule.num_train_timesteps)
        std = self.policy.schedule.ddim_std(t, t_prev, self.policy.eta, torch.zeros(1))
        keep = torch.nonzero(std.reshape(-1) > 1e-4).reshape(-1)
        return keep if len(keep) else torch.arange(len(t))

    def kl_to_base(self, batch: TensorDict) -> torch.Tensor:
        """KL(pi_theta || pi_ref) of the step Gaussians (equal variances): mean ||mu - mu_ref||^2 / (2 sigma^2),
        pi_ref the policy's :meth:`~agents.policy.DiffusionPolicy.reference_policy`."""
        mean, std = self.policy(batch["x_t"], batch["t"], batch["floor"], batch.get("classes", None))
        with torch.no_grad(), self.policy.reference_policy():
            base, _ = self.policy(batch["x_t"], batch["t"], batch["floor"])
        return ((mean - base) ** 2 / (2 * std**2)).flatten(1).mean(1).mean()

    # --- the SB3 surface ------------------------------------------------------------------------------
    def learn(self, total_timesteps: int, callback=None, progress_bar: bool = False,
              reset_num_timesteps: bool = False) -> "DDPO":
        """Train until ``num_timesteps`` (environment transitions: scenes x DDIM steps) reaches
        ``total_timesteps``. Continues from the current counters (resume after :meth:`load`). Under
        ``torchrun`` the counters are per rank, and the callbacks and the progress bar run on rank 0 only."""
        from tqdm import tqdm

        if reset_num_timesteps:
            self.num_timesteps, self.epoch = 0, 0
        main = distributed.is_main()
        cb = as_callback(callback if main else None)
        cb.init_callback(self)
        cb.on_training_start()
        self._log_hparams()
        bar = tqdm(total=total_timesteps, initial=min(self.num_timesteps, total_timesteps), unit="step",
                   desc=self.name, disable=not (progress_bar and main))
        while self.num_timesteps < total_timesteps:
            t0 = time.perf_counter()
            before = self.num_timesteps
            rollouts = [self.collect_rollouts() for _ in range(self.config.num_batches_per_epoch)]
            rollout = torch.cat(rollouts, 0)
            rewards = rollout["reward"][:, 0]
            self.set_advantages(rollout)
            t1 = time.perf_counter()
            everyone = distributed.all_gather(rewards)  # the statistics of every rank's scenes
            stats = {"reward_mean": float(everyone.mean()), "reward_std": float(everyone.std())}
            if self._last_terms:
                means = torch.tensor([[np.mean(v) for v in self._last_terms.values()]], dtype=torch.float64)
                stats.update({f"reward_{k}": float(m)
                              for k, m in zip(self._last_terms, distributed.all_gather(means).mean(0))})
            if "reward_x0_hat" in rollout.keys():
                stats["x0_baseline_r2"] = self._x0_r2
            cb.on_rollout_end(stats)
            stats.update(self.train(rollout))
            self.epoch += 1
            stats.update({"time_rollout": t1 - t0, "time_update": time.perf_counter() - t1,
                          "learning_rate": self.optimizer.param_groups[0]["lr"]})
            self._log(stats)
            bar.update(self.num_timesteps - before)
            bar.set_postfix(reward=f"{stats['reward_mean']:.3f}", kl=f"{stats['approx_kl']:.1e}")
            keep_going = distributed.broadcast_object(cb.on_step(stats))
            self._sync_reward()
            if not keep_going:
                break
        bar.close()
        cb.on_training_end()
        if self._writer:
            self._writer.flush()
        return self

    def _sync_reward(self) -> None:
        """Under ``torchrun`` the callbacks run on rank 0 only; the reward they may change (reflection swaps the
        task program and its weight) is copied from there to the other ranks."""
        if distributed.world_size() == 1:
            return
        fn = self.venv.reward_fn
        programs = {name: f.code for name, f in getattr(fn, "functions", {}).items() if hasattr(f, "load")}
        state = distributed.broadcast_object({"weights": getattr(fn, "weights", None), "programs": programs})
        if distributed.is_main():
            return
        if state["weights"] is not None:
            fn.weights.update(state["weights"])
        for name, code in state["programs"].items():
            if fn.functions[name].code != code:
                fn.functions[name].load(code)

    def predict(self, observation: dict, deterministic: bool = False) -> tuple[np.ndarray, None]:
        """The next state x_{t-1} for an observation (batched or not), as numpy, SB3-style ``(action, None)``."""
        x = torch.as_tensor(observation["x_t"], dtype=torch.float32)
        single = x.ndim == 2
        t = torch.as_tensor(observation["t"]).reshape(-1)
        f = torch.as_tensor(observation["floor"], dtype=torch.float32)
        if single:
            x, f = x[None], f[None]
        on = self.device
        action, _ = self.policy.act(x.to(on), t.to(on), f.to(on), generator=self.generator,
                                    deterministic=deterministic)
        action = action.cpu().numpy()
        return (action[0] if single else action), None

    @torch.no_grad()
    def evaluate(self, floors, seed: int = 0, n_render: int = 16, scene_metrics=None) -> dict[str, float]:
        """Sample scenes on ``floors`` with the current adapter; metrics, objects per room (``mean_objects``,
        and ``mean_ground_objects`` without lamps: a policy that empties the rooms, or swaps furniture for
        pendant lamps, shows there first) and reward, logged to TensorBoard.
        ``scene_metrics`` ``{name: f(SceneBatch) -> float}`` adds metrics (e.g. a task's success rate)."""
        from iarcs_env.metrics import evaluate_layouts
        from iarcs_env.render import render_layout

        scenes = self.policy.sample(floors, generator=torch.Generator().manual_seed(seed))
        layouts = scenes.to_layouts()
        measured = evaluate_layouts(layouts)
        metrics = {k: float(measured[k]) for k in LOWER_IS_BETTER + HIGHER_IS_BETTER}
        total, terms = evaluate_reward(self.venv.reward_fn, scenes)
        metrics["reward"] = float(total.mean())
        metrics.update({name: float(fn(scenes)) for name, fn in (scene_metrics or {}).items()})
        metrics.update({f"reward_{k}": float(v.mean()) for k, v in terms.items()})
        if self.writer:
            for k, v in metrics.items():
                self.writer.add_scalar(f"eval/{k}", v, self.num_timesteps)
            if n_render:
                grid = render_grid_tensor([render_layout(l) for l in layouts[:n_render]])
                self.writer.add_image("eval/scenes", grid, self.num_timesteps)
        return metrics

    # --- logging ---------------------------------------------------------------------------------------
    @property
    def writer(self):
        if self._writer is None and self.tensorboard_log is not None:
            from torch.utils.tensorboard import SummaryWriter

            self._writer = SummaryWriter(str(self.tensorboard_log))
        return self._writer

    def _log_hparams(self) -> None:
        if self.writer and self.epoch == 0:
            text = "\n".join(f"    {k}: {v}" for k, v in {"algorithm": self.name, "adapter": self.policy.adapter,
                                                           "num_envs": self.venv.num_envs,
                                                           "num_steps": self.venv.num_steps,
                                                           **asdict(self.config)}.items())
            self.writer.add_text("hyperparameters", text, 0)

    def _log(self, stats: dict) -> None:
        if self.verbose >= 2:
            print(f"epoch {self.epoch}: " + ", ".join(f"{k}={v:.4g}" for k, v in stats.items()))
        if not self.writer:
            return
        groups = {"reward": "rollout", "clip_fraction": "train", "approx_kl": "train", "loss": "train",
                  "grad_norm": "train", "kl_to_base": "train", "learning_rate": "train", "time": "time"}
        for k, v in stats.items():
            group = next((g for p, g in groups.items() if k.startswith(p)), "train")
            self.writer.add_scalar(f"{group}/{k}", v, self.num_timesteps)

    # --- persistence -----------------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Everything needed to resume: the adapter (peft format), optimiser, counters and random states.

        Crash-safe: written to ``path.tmp``, then swapped in; a kill at any moment leaves either ``path`` or
        ``path.old`` complete (:meth:`load` falls back to the latter)."""
        import shutil

        path = Path(path)
        tmp, old = path.with_name(path.name + ".tmp"), path.with_name(path.name + ".old")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        self.policy.save_adapter(tmp / "adapter")
        state = {"algorithm": self.name, "config": asdict(self.config), "epoch": self.epoch,
                 "num_timesteps": self.num_timesteps, "adapter": self.policy.adapter,
                 "optimizer": self.optimizer.state_dict(), "rng": self.rng.bit_generator.state,
                 "generator": self.generator.get_state(), "env_rng": self.venv.np_random.bit_generator.state,
                 "env_seeded": self._env_seeded}
        torch.save(state, tmp / "trainer_state.pt")
        (tmp / "trainer.json").write_text(json.dumps({k: state[k] for k in ("algorithm", "config", "epoch",
                                                                            "num_timesteps", "adapter")}, indent=1))
        if (path / "trainer_state.pt").exists():
            shutil.rmtree(old, ignore_errors=True)
            path.rename(old)
        else:
            shutil.rmtree(path, ignore_errors=True)
        tmp.rename(path)
        shutil.rmtree(old, ignore_errors=True)
        return path

    @staticmethod
    def latest_checkpoint(path: str | Path) -> Path | None:
        """``path`` if it holds a complete checkpoint, else ``path.old`` (a kill during a save), else None."""
        path = Path(path)
        for candidate in (path, path.with_name(path.name + ".old")):
            if (candidate / "trainer_state.pt").exists():
                return candidate
        return None

    @classmethod
    def load(cls, path: str | Path, policy: DiffusionPolicy, env, **kwargs) -> "DDPO":
        """Resume from :meth:`save`: loads the adapter into ``policy`` and restores the trainer's state."""
        found = cls.latest_checkpoint(path)
        if found is None:
            raise FileNotFoundError(f"no training checkpoint in {path} (trainer_state.pt missing)")
        path = found
        state = torch.load(path / "trainer_state.pt", map_location="cpu", weights_only=False)
        name = state["adapter"]
        policy.load_adapter(path / "adapter" / name, name)
        algo = algorithm_class(state["algorithm"], cls)
        model = algo(policy, env, config=DDPOConfig.from_dict(state["config"]), **kwargs)
        model.optimizer.load_state_dict(state["optimizer"])
        model.epoch, model.num_timesteps = state["epoch"], state["num_timesteps"]
        model.rng.bit_generator.state = state["rng"]
        model.generator.set_state(state["generator"])
        model.venv.np_random.bit_generator.state = state["env_rng"]
        model._env_seeded = state["env_seeded"]
        if distributed.rank() > 0:  # rank 0's streams were saved; the others start new ones from here
            model._seed = distributed.rank_seed(model.config.seed) + model.epoch
            model.rng = np.random.default_rng(model._seed)
            model.generator.manual_seed(model._seed)
            model._env_seeded = False
        return model


def algorithm_class(name: str, base: type) -> type:
    """The class among ``base`` and its subclasses whose ``name`` is ``name`` (a checkpoint's algorithm); import the
    module defining it first (:mod:`agents.algorithms` imports them all)."""
    classes, found = [base], None
    while classes:
        cls = classes.pop()
        found = cls if cls.name == name else found
        classes += cls.__subclasses__()
    if found is None:
        raise ValueError(f"the checkpoint was trained with {name!r}, which no imported algorithm is; "
                         "`import agents.algorithms` loads them all")
    return found


class DDPOSF(DDPO):
    """DDPO-SF: the score-function (REINFORCE) estimator, ``loss = -mean(A * log pi_theta(x_{t-1}|x_t))``,
    on-policy (use num_inner_epochs = 1). Same interface as :class:`DDPO`."""

    name = "DDPO-SF"

    def policy_loss(self, batch: TensorDict) -> tuple[torch.Tensor, dict[str, float]]:
        log_prob = self.policy.log_prob(batch["x_t"], batch["t"], batch["floor"], batch["action"],
                                        batch.get("classes", None))
        adv = batch["advantage"].reshape(-1)
        loss = -(adv * log_prob).mean()
        approx_kl = float((batch["sample_log_prob"] - log_prob.detach()).mean())
        return loss, {"clip_fraction": 0.0, "approx_kl": approx_kl}
