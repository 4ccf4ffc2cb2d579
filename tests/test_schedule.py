"""The noise schedule: forward noising, DDIM steps, their Gaussians and mean-reduced log-probabilities."""

from __future__ import annotations

import math

import pytest
import torch

from iarcs_env.schedule import (MIN_STD, NoiseSchedule, classifier_free_guidance, gaussian_log_prob,
                                guided_model_fn)

SHAPE = (3, 12, 30)  # B scenes, N slots, 8 + K features (bedroom: K = 22)


def _direct_gaussian(sched: NoiseSchedule, eps, t: int, t_prev: int, x_t, eta: float):
    """Mean and std of the DDIM step, computed independently of NoiseSchedule.step (float64)."""
    ac = sched.alphas_cumprod.double()
    a_t = ac[t]
    a_prev = ac[t_prev] if t_prev >= 0 else torch.tensor(1.0, dtype=torch.float64)
    x_t, eps = x_t.double(), eps.double()
    x0 = ((x_t - math.sqrt(1 - a_t) * eps) / math.sqrt(a_t)).clamp(-1, 1)
    var = (1 - a_prev) / (1 - a_t) * (1 - a_t / a_prev)
    sigma = eta * math.sqrt(max(float(var), 0.0))
    mean = math.sqrt(a_prev) * x0 + math.sqrt(max(float(1 - a_prev - sigma**2), 0.0)) * eps
    return mean, max(sigma, MIN_STD)


def test_linear_betas_and_alpha_bar():
    s = NoiseSchedule()
    assert s.betas.shape == (1000,)
    assert s.betas[0].item() == pytest.approx(1e-4) and s.betas[-1].item() == pytest.approx(0.02)
    assert torch.allclose(s.alphas_cumprod, torch.cumprod(1 - s.betas.double(), 0).float())
    assert 0 < s.alphas_cumprod[-1] < 1e-4  # x_T is almost pure noise


def test_q_sample_formula_and_scalar_or_batched_t():
    s = NoiseSchedule()
    x0, noise = torch.rand(SHAPE) * 2 - 1, torch.randn(SHAPE)
    t = torch.tensor([0, 400, 999])
    xt = s.q_sample(x0, t, noise)
    for i, ti in enumerate(t):
        a = s.alphas_cumprod[ti]
        assert torch.allclose(xt[i], a.sqrt() * x0[i] + (1 - a).sqrt() * noise[i], atol=1e-6)
    assert torch.allclose(s.q_sample(x0, 400, noise), s.q_sample(x0, torch.full((3,), 400), noise))


def test_training_loss_is_zero_for_a_perfect_model_and_one_for_zero():
    s = NoiseSchedule()
    x0, noise = torch.rand(SHAPE) * 2 - 1, torch.randn(SHAPE)
    assert s.training_loss(lambda x, t: noise, x0, noise=noise).item() == 0.0
    zero = s.training_loss(lambda x, t: torch.zeros_like(x), x0, noise=noise, reduction="none")
    assert zero.shape == (3,) and torch.allclose(zero, (noise**2).flatten(1).mean(1))


def test_feature_weights_scale_the_squared_error_of_their_features_only():
    s = NoiseSchedule()
    x0, noise = torch.rand(SHAPE) * 2 - 1, torch.randn(SHAPE)
    weights = torch.ones(SHAPE[-1])
    weights[[0, 2]] = 10.0
    plain = s.training_loss(lambda x, t: torch.zeros_like(x), x0, noise=noise, reduction="none")
    weighted = s.training_loss(lambda x, t: torch.zeros_like(x), x0, noise=noise, reduction="none",
                               feature_weights=weights)
    extra = 9.0 * (noise[..., [0, 2]] ** 2).sum(-1).sum(-1) / noise[0].numel()
    assert torch.allclose(weighted, plain + extra, atol=1e-5)
    assert s.training_loss(lambda x, t: noise, x0, noise=noise, feature_weights=weights).item() == 0.0


@pytest.mark.parametrize("steps", [1, 7, 20, 50, 1000])
def test_set_timesteps_any_number_descending_to_zero(steps):
    s = NoiseSchedule()
    ts = s.set_timesteps(steps)
    assert len(ts) == steps and ts[-1] == 0 and ts[0] < 1000
    assert torch.all(ts[:-1] > ts[1:])
    assert s.previous_timestep(ts[-1]) < 0


@pytest.mark.parametrize("t", [950, 500, 50, 0])
@pytest.mark.parametrize("eta", [1.0, 0.5])
def test_step_log_prob_equals_direct_gaussian_density(t, eta):
    s = NoiseSchedule()
    s.set_timesteps(20)
    g = torch.Generator().manual_seed(t)
    x_t, eps, nxt = torch.randn(SHAPE, generator=g), torch.randn(SHAPE, generator=g), torch.randn(SHAPE, generator=g)
    out = s.step(eps, t, x_t, eta=eta, prev_sample=nxt)
    mean, std = _direct_gaussian(s, eps, t, t - 50, x_t, eta)
    assert torch.allclose(out.mean.double(), mean, atol=1e-5)
    assert torch.allclose(out.std.double().expand(SHAPE), torch.full(SHAPE, std, dtype=torch.float64), rtol=1e-5)
    direct = torch.distributions.Normal(mean, std).log_prob(nxt.double()).flatten(1).mean(1)
    if t > 0:
        assert torch.allclose(out.log_prob.double(), direct, rtol=1e-4)
    else:  # std = 1e-6: huge negative numbers, compare relatively and check they are finite
        assert torch.isfinite(out.log_prob).all()
        assert torch.allclose(out.log_prob.double(), direct, rtol=1e-3)
    assert out.log_prob.shape == (3,)
    assert torch.equal(out.prev_sample, nxt)


def test_log_prob_is_mean_not_sum_over_elements():
    x = torch.zeros(2, 4, 5)
    lp = gaussian_log_prob(x, torch.zeros_like(x), torch.ones(2, 1, 1))
    assert torch.allclose(lp, torch.full((2,), -0.5 * math.log(2 * math.pi)))


def test_sampled_state_log_prob_matches_under_eta_one():
    s = NoiseSchedule()
    s.set_timesteps(20)
    x_t, eps = torch.randn(SHAPE), torch.randn(SHAPE)
    t = torch.full((3,), 600)
    out = s.step(eps, t, x_t, eta=1.0, generator=torch.Generator().manual_seed(1))
    again = s.step(eps, t, x_t, eta=1.0, prev_sample=out.prev_sample)
    assert torch.allclose(out.log_prob, again.log_prob)
    normal = torch.distributions.Normal(out.mean, out.std)
    assert torch.allclose(out.log_prob, normal.log_prob(out.prev_sample).flatten(1).mean(1), atol=1e-5)
    # a draw from N(mean, std): standardised residuals look standard normal
    z = (out.prev_sample - out.mean) / out.std
    assert abs(z.mean().item()) < 0.2 and abs(z.std().item() - 1) < 0.2


def test_last_step_has_no_zero_variance():
    s = NoiseSchedule()
    s.set_timesteps(20)
    x_t, eps = torch.randn(SHAPE), torch.randn(SHAPE)
    out = s.step(eps, 0, x_t, eta=1.0, generator=torch.Generator().manual_seed(0))
    assert torch.all(out.std == MIN_STD)
    assert torch.isfinite(out.log_prob).all()
    off = s.step(eps, 0, x_t, eta=1.0, prev_sample=out.mean + 1e-3)
    assert torch.isfinite(off.log_prob).all() and (off.log_prob < out.log_prob).all()
    # the final alpha-bar is 1: the mean is the (clipped) x0 estimate itself
    assert torch.allclose(out.mean, out.pred_original_sample, atol=1e-6)


def test_eta_zero_is_deterministic():
    s = NoiseSchedule()
    model = lambda x, t: 0.5 * x  # noqa: E731 - any deterministic eps model
    x_T = torch.randn(SHAPE)
    a = s.sample(model, SHAPE, num_steps=10, eta=0.0, generator=torch.Generator().manual_seed(0), x_T=x_T)
    b = s.sample(model, SHAPE, num_steps=10, eta=0.0, generator=torch.Generator().manual_seed(99), x_T=x_T)
    assert torch.equal(a, b)
    out = s.step(torch.randn(SHAPE), 500, x_T, eta=0.0)
    assert torch.equal(out.prev_sample, out.mean) and torch.isfinite(out.log_prob).all()
    c = s.sample(model, SHAPE, num_steps=10, eta=1.0, generator=torch.Generator().manual_seed(0), x_T=x_T)
    assert not torch.equal(a, c)


def test_rollout_trajectory_and_seeded_reproducibility():
    s = NoiseSchedule()
    model = lambda x, t: 0.1 * x  # noqa: E731
    x0, traj = s.sample(model, SHAPE, num_steps=20, eta=1.0, generator=torch.Generator().manual_seed(3),
                        return_trajectory=True)
    assert traj["states"].shape == (21,) + SHAPE and traj["log_probs"].shape == (20, 3)
    assert torch.equal(traj["states"][-1], x0) and torch.isfinite(traj["log_probs"]).all()
    assert torch.equal(traj["timesteps"], torch.arange(19, -1, -1) * 50)
    again = s.sample(model, SHAPE, num_steps=20, eta=1.0, generator=torch.Generator().manual_seed(3))
    assert torch.equal(x0, again)
    # each recorded log-prob is that of the recorded next state
    k = 7
    t = torch.full((3,), int(traj["timesteps"][k]))
    st = traj["states"]
    re = s.step(model(st[k], t), t, st[k], eta=1.0, prev_sample=st[k + 1])
    assert torch.allclose(re.log_prob, traj["log_probs"][k])


def test_clip_sample_option():
    s = NoiseSchedule()
    s.set_timesteps(20)
    x_t, eps = 5 * torch.randn(SHAPE), torch.randn(SHAPE)
    assert s.step(eps, 900, x_t, eta=0.0).pred_original_sample.abs().max() <= 1.0
    assert s.step(eps, 900, x_t, eta=0.0, clip_sample=False).pred_original_sample.abs().max() > 1.0


def test_classifier_free_guidance():
    e_c, e_u = torch.randn(SHAPE), torch.randn(SHAPE)
    assert torch.allclose(classifier_free_guidance(e_c, e_u, 1.0), e_c, atol=1e-6)
    assert torch.allclose(classifier_free_guidance(e_c, e_u, 3.0), e_u + 3 * (e_c - e_u), atol=1e-6)
    calls = []

    def model(x, t, cond):
        calls.append(x.shape[0])
        return x * cond.mean(dim=(1, 2))[:, None, None]

    cond = torch.rand(3, 256, 4) + 1
    x, t = torch.randn(SHAPE), torch.full((3,), 10)
    assert torch.allclose(guided_model_fn(model, cond, 1.0)(x, t), model(x, t, cond))
    calls.clear()
    g = guided_model_fn(model, cond, 2.0)(x, t)
    assert calls == [6]  # one doubled batch: conditional and unconditional (zeroed floor)
    assert torch.allclose(g, 2 * model(x, t, cond) - model(x, t, torch.zeros_like(cond)), atol=1e-6)


def test_unknown_schedule_options_fail_clearly():
    with pytest.raises(ValueError, match="linear"):
        NoiseSchedule(beta_schedule="cosine")
    with pytest.raises(ValueError, match=r"number of DDIM steps \(num_steps\) must be in 1..1000; got 0"):
        NoiseSchedule().set_timesteps(0)


def test_the_ddim_grid_has_one_home_that_the_schedule_environment_policy_and_ddpo_share():
    """The environment's timesteps and the policy's previous timesteps are the schedule's grid."""
    import gymnasium as gym

    from iarcs_env.schedule import ddim_previous, ddim_timesteps

    assert ddim_timesteps(20).tolist() == list(range(950, -1, -50))
    assert ddim_timesteps(3).tolist() == [666, 333, 0] and ddim_previous(0, 3).item() == -333
    sched = NoiseSchedule()
    assert torch.equal(sched.set_timesteps(7), ddim_timesteps(7))
    assert sched.previous_timestep(sched.timesteps).tolist() == ddim_previous(ddim_timesteps(7), 7).tolist()
    env = gym.make_vec("iARCS-Bedroom-v0", num_envs=2, vectorization_mode="vector_entry_point", num_steps=7)
    assert env.unwrapped.timesteps.tolist() == ddim_timesteps(7).tolist()
    with pytest.raises(ValueError, match=r"DDIM steps \(num_steps\) must be in 1..1000; got 1001"):
        gym.make("iARCS-Bedroom-v0", num_steps=1001)
