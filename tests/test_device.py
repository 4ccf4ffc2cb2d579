"""Where the networks run: device settings and their errors on every machine; the GPU path (pretraining,
sampling, DDPO, resuming across devices) where torch sees a CUDA GPU."""

import json

import pytest
import torch

from agents.config import check_device, resolve_device
from agents.pretrain import PRIOR_FILE, PretrainConfig, train
from experiments.cli import main
from iarcs_env.schedule import standard_normal

HAS_CUDA = torch.cuda.is_available()
needs_cuda = pytest.mark.skipif(not HAS_CUDA, reason=f"torch {torch.__version__} sees no CUDA GPU on this machine")
no_cuda = pytest.mark.skipif(HAS_CUDA, reason="checks the errors of a machine without a CUDA GPU")


def test_device_settings_are_checked():
    assert [check_device(d) for d in ("auto", "CPU", "cuda", " cuda:1")] == ["auto", "cpu", "cuda", "cuda:1"]
    for bad in ("gpu", "tpu", "cuda:", "cuda:x", "mps"):
        with pytest.raises(ValueError, match=f"device '{bad}' is not one iARCS runs on; use auto, cpu, cuda or"):
            check_device(bad)
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if HAS_CUDA else "cpu")
    with pytest.raises(ValueError, match="device 'gpu'"):
        PretrainConfig(device="gpu")


def test_seeded_noise_is_drawn_on_the_generators_device():
    g = lambda: torch.Generator().manual_seed(3)  # noqa: E731
    where = resolve_device("auto")
    a = standard_normal((4, 5), g(), where)
    assert a.device.type == where.type
    assert torch.equal(a.cpu(), torch.randn((4, 5), generator=g()))  # the same numbers wherever the model runs


@no_cuda
def test_asking_for_a_gpu_without_one_is_a_clear_error(tmp_path, capsys):
    for name in ("cuda", "cuda:1"):
        with pytest.raises(ValueError, match=f"device '{name}' asked for, but torch .* sees no CUDA GPU.*use device "
                                             "auto or cpu"):
            resolve_device(name)
    out = tmp_path / "s.json"
    assert main(["sample", "--num-scenes", "2", "--steps", "2", "--device", "cuda", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("iarcs: error: device 'cuda' asked for") and "Traceback" not in err and not out.exists()
    assert main(["sample", "--num-scenes", "2", "--steps", "2", "--device", "gpu", "--out", str(out)]) == 2
    assert "use auto, cpu, cuda or cuda:N" in capsys.readouterr().err
    assert main(["sample", "--num-scenes", "2", "--steps", "2", "--device", "cpu", "--out", str(out)]) == 0
    assert len(json.loads(out.read_text())["scenes"]) == 2


@needs_cuda
def test_pretraining_on_a_gpu_resumes_on_the_cpu(tmp_path):
    from test_pretrain import tiny_config, toy_bedrooms

    rooms = toy_bedrooms(40)
    gpu = train(tiny_config(tmp_path, device="cuda", steps=10), layouts=rooms, progress=False, log=lambda m: None)
    assert gpu.step == 10 and all(torch.isfinite(torch.tensor(v)) for _, v in gpu.losses)
    more = train(tiny_config(tmp_path, device="cpu", steps=14), layouts=rooms, progress=False, log=lambda m: None)
    assert more.resumed_from == 10 and more.step == 14

    from agents.denoiser import ScenePrior
    from iarcs_env.datasets.procedural import generate_layouts

    prior = ScenePrior.load(tmp_path / "run" / PRIOR_FILE)
    floors = [l.floor for l in generate_layouts("bedroom", 6, seed=3)]
    cpu = prior.sample(floors, num_steps=5, generator=torch.Generator().manual_seed(1))
    on_gpu = prior.to("cuda").sample(floors, num_steps=5, generator=torch.Generator().manual_seed(1))
    assert torch.equal(cpu.labels, on_gpu.labels)  # the same seeded noise; only float rounding differs
    torch.testing.assert_close(cpu.translations, on_gpu.translations, atol=1e-3, rtol=1e-3)


@needs_cuda
def test_ddpo_trains_on_a_gpu_and_resumes_on_the_cpu(tmp_path):
    from test_ddpo import STEPS, adapter_weights, make_env, make_model, tiny_prior

    from agents.callbacks import CheckpointCallback
    from agents.ddpo import DDPO
    from agents.policy import DiffusionPolicy

    model = make_model()
    model.policy.to("cuda")  # after the trainer was made: its optimiser holds the same (moved) parameters
    before = {k: v.cpu() for k, v in adapter_weights(model).items()}
    model.learn(8 * STEPS * 2, callback=CheckpointCallback(1, tmp_path / "ckpt"))
    assert model.device.type == "cuda"
    after = adapter_weights(model)
    assert any(not torch.equal(before[k], after[k].cpu()) for k in before)  # it learned on the GPU
    resumed = DDPO.load(tmp_path / "ckpt", DiffusionPolicy(tiny_prior(), num_steps=STEPS), make_env(), verbose=0)
    assert resumed.device.type == "cpu" and resumed.epoch == 2
    for k, v in adapter_weights(resumed).items():
        torch.testing.assert_close(v, after[k].cpu())
    resumed.learn(8 * STEPS * 3)
    assert resumed.epoch == 3


def test_info_reports_the_device_models_library_and_agent(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("IARCS_HOME", str(tmp_path))
    (tmp_path / "adapters" / "bedroom" / "a_wheelchair_accessible_bedroom-1234abcd" / "adapter").mkdir(parents=True)
    for key in ("GEMINI_API_KEY", "OPENAI_API_KEY", "ANTHROPIC_API_KEY", "OPENAI_API_BASE"):
        monkeypatch.delenv(key, raising=False)
    assert main(["info"]) == 0
    text = capsys.readouterr().out
    assert f"`device: auto` trains on {resolve_device('auto')}" in text
    assert f"torch {torch.__version__}" in text and "gloo" in text
    assert "bedroom: prior " in text and "bedroom_small.pt; stage-1 adapter " in text
    assert "livingroom: prior " in text and "stage-1 adapter not shipped" in text
    assert "bedroom/a_wheelchair_accessible_bedroom-1234abcd" in text
    assert "the offline planner writes the reward programs" in text

    monkeypatch.setenv("GEMINI_API_KEY", "k")
    assert main(["info", "--json"]) == 0
    facts = json.loads(capsys.readouterr().out)
    assert facts["llm_keys_set"] == ["GEMINI_API_KEY"] and facts["device"]["auto"] == str(resolve_device("auto"))
    assert facts["packages"]["torch"] == torch.__version__ and len(facts["device"]["gpus"]) == torch.cuda.device_count()


@needs_cuda
def test_the_pretraining_step_never_waits_for_the_gpu():
    """A training step on CUDA (batch drawn and augmented on the device, losses, backward, fused AdamW, EMA)
    queues its work without one host synchronisation: torch's sync debug mode turns any into an error."""
    import copy
    from dataclasses import replace

    from agents.denoiser import SceneDenoiser
    from agents.pretrain import draw_batch, load_config, loss_feature_weights, training_step
    from agents.pretrain_data import SceneTensors, stats_for_training
    from iarcs_env import get_room
    from iarcs_env.schedule import NoiseSchedule
    from test_pretrain import toy_bedrooms

    cfg = load_config("experiments/pretrain_bedroom_gpu.yaml", batch_size=64, precision="bf16")
    spec, rooms, device = get_room("bedroom"), toy_bedrooms(80), torch.device("cuda")
    stats = replace(stats_for_training(rooms, "bedroom", True), translation_frame="room")
    data = SceneTensors.from_layouts(rooms, spec.max_objects).to(device)
    net = SceneDenoiser(cfg.denoiser_config(), spec.feature_dim).to(device)
    net.set_metric_scale(stats)
    ema = copy.deepcopy(net).requires_grad_(False)
    opt = torch.optim.AdamW(net.parameters(), lr=1e-4, fused=True)
    weights = loss_feature_weights(cfg, spec.feature_dim).to(device)
    gen, schedule = torch.Generator(device).manual_seed(0), NoiseSchedule()
    step = lambda: training_step(net, net, ema, opt, schedule, cfg, spec, stats, weights,  # noqa: E731
                                 lambda: draw_batch(data, cfg, spec, stats, gen, 64), 1e-4, 0.999)
    step()  # first calls may set things up (constants moved to the device, kernels chosen)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(3):
            loss, grad_norm = step()
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert torch.isfinite(loss) and torch.isfinite(grad_norm)
