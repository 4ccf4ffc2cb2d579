"""Pretraining: configs, augmentation, loss going down, resuming an interrupted run, and the CLI."""

from __future__ import annotations

import copy
import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from agents.denoiser import ScenePrior
from agents.pretrain import (PRIOR_FILE, STATE_FILE, PretrainConfig, config_from_dict, load_config,
                             loss_feature_weights, lr_at, train)
from agents.x0_losses import out_of_bound_excess, overlap_excess
from agents.pretrain_data import SceneTensors, encode_batch, resolve_dataset, stats_for_training
from iarcs_env import FloorPlan, Layout, get_room
from iarcs_env.datasets import save_layouts
from iarcs_env.scene import SceneBatch, floor_features

BEDROOM = get_room("bedroom")


def toy_bedrooms(n: int, seed: int = 0) -> list[Layout]:
    """Rectangular rooms with a bed against the back wall and a few random objects (no generator needed)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        w, d = rng.uniform(3, 5), rng.uniform(3, 4.5)
        x0, z0 = rng.uniform(-2, 2, size=2)
        floor = FloorPlan.from_vertices([(x0, z0), (x0 + w, z0), (x0 + w, z0 + d), (x0, z0 + d)])
        labels, trans, half, yaws = ["double_bed"], [[x0 + w / 2, 0.4, z0 + 1.1]], [[0.9, 0.4, 1.0]], [0.0]
        for _ in range(rng.integers(0, 5)):
            labels.append(str(rng.choice(["nightstand", "wardrobe", "pendant_lamp", "chair"])))
            trans.append([x0 + rng.uniform(0.4, w - 0.4), rng.uniform(0.2, 2.0), z0 + rng.uniform(0.4, d - 0.4)])
            half.append(list(rng.uniform(0.15, 0.5, size=3)))
            yaws.append(float(rng.choice([0, np.pi / 2, np.pi, -np.pi / 2])))
        out.append(Layout("bedroom", floor, labels, trans, half, yaws, id=f"toy_{i}"))
    return out


@pytest.fixture(autouse=True)
def data_cache(tmp_path, monkeypatch):
    """Procedural rooms' data cached in the test's folder, not the working directory's out/cache."""
    monkeypatch.setenv("IARCS_CACHE_DIR", str(tmp_path / "cache"))


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def tiny_config(tmp_path, **kw) -> PretrainConfig:
    base = dict(preset="tiny", steps=30, batch_size=16, lr=3e-3, warmup_steps=2, checkpoint_every=10,
                log_every=5, eval_every=10, val_scenes=8, out=str(tmp_path / "run"), tensorboard=False,
                device="cpu")  # exact comparisons; the GPU path is tests/test_device.py's
    base.update(kw)
    return PretrainConfig(**base)


def test_config_yaml_round_trip_and_clear_errors(tmp_path):
    cfg = load_config("experiments/pretrain_bedroom.yaml")
    assert cfg.room == "bedroom" and cfg.dataset == "procedural" and cfg.preset == "small"
    assert load_config("experiments/pretrain_bedroom.yaml", steps=7, out="x").steps == 7
    for name in ("livingroom", "diningroom", "bedroom_real", "bedroom_paper"):
        load_config(f"experiments/pretrain_{name}.yaml")
    with pytest.raises(ValueError, match=r"unknown key 'stpes' \(did you mean 'steps'\?\)"):
        config_from_dict({"stpes": 3})
    with pytest.raises(ValueError, match="batch_size must be a int"):
        config_from_dict({"batch_size": "big"})
    with pytest.raises(ValueError, match="unknown room type"):
        config_from_dict({"room": "kitchen"})
    with pytest.raises(ValueError, match="precision must be fp32 or bf16, got 'fp16'"):
        config_from_dict({"precision": "fp16"})
    with pytest.raises(ValueError, match="unknown denoiser field"):
        config_from_dict({"model": {"layers": 3}})
    assert config_from_dict({"lr": 1}).lr == 1.0  # ints are fine where floats are expected
    bad = tmp_path / "bad.yaml"
    bad.write_text("- a\n- b\n")
    with pytest.raises(ValueError, match="mapping"):
        load_config(bad)
    with pytest.raises(FileNotFoundError, match="no config file"):
        load_config(tmp_path / "none.yaml")


def test_every_config_field_has_a_docstring():
    import ast
    import inspect

    import agents.pretrain as mod

    tree = ast.parse(inspect.getsource(mod.PretrainConfig))
    body = tree.body[0].body
    documented = {body[i].target.id for i in range(len(body) - 1)
                  if isinstance(body[i], ast.AnnAssign) and isinstance(body[i + 1], ast.Expr)}
    assert documented == {f for f in PretrainConfig.__dataclass_fields__}


def test_dataset_paths_resolve_from_cwd_or_repository(tmp_path, monkeypatch):
    assert resolve_dataset("procedural") == "procedural"
    monkeypatch.chdir(tmp_path)
    assert resolve_dataset("experiments/pretrain_bedroom.yaml").endswith("experiments/pretrain_bedroom.yaml")
    with pytest.raises(FileNotFoundError, match="looked at"):
        resolve_dataset("nowhere/rooms.json")


def test_tensor_rotation_matches_layout_rotated():
    lays = toy_bedrooms(6, seed=1)
    stats = stats_for_training(lays, "bedroom", rotation_augment=True)
    data = SceneTensors.from_layouts(lays, 12)
    k = torch.randint(0, 4, (6,), generator=torch.Generator().manual_seed(5))
    batch = data.batch(torch.arange(6), torch.Generator().manual_seed(5), rotate=True)
    x0, floor = encode_batch(BEDROOM, stats, *batch)
    ref = SceneBatch.from_layouts([l.centred().rotated(int(ki) * math.pi / 2) for l, ki in zip(lays, k)],
                                  num_slots=12)
    assert torch.allclose(x0, ref.encode(stats), atol=1e-5)
    ref_floor = floor_features(ref.floors, stats)
    # the same boundary point set (possibly from another start vertex): compare as sets
    for a, b in zip(floor, ref_floor):
        d = torch.cdist(a, b)
        assert d.min(1).values.max() < 5e-3


def test_permutation_augmentation_keeps_the_scene():
    lays = toy_bedrooms(4)
    data = SceneTensors.from_layouts(lays, 12)
    labels, trans, *_ = data.batch(torch.arange(4), torch.Generator().manual_seed(0), permute=True)
    assert not torch.equal(labels, data.labels)
    assert torch.equal(labels.sort(1).values, data.labels.sort(1).values)
    assert torch.allclose(trans.sum(1), data.translations.sum(1), atol=1e-5)


def test_lr_schedule_warms_up_and_decays():
    cfg = PretrainConfig(steps=100, warmup_steps=10, lr=1e-3, min_lr_ratio=0.1)
    assert lr_at(0, cfg) == pytest.approx(1e-4) and lr_at(9, cfg) == pytest.approx(1e-3)
    assert lr_at(99, cfg) == pytest.approx(1e-4, rel=0.01)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_pretraining_lowers_the_loss(tmp_path, precision):
    cfg = tiny_config(tmp_path, steps=60, precision=precision)
    result = train(cfg, toy_bedrooms(80), progress=False, log=lambda m: None)
    losses = [v for _, v in result.losses]  # the mean loss of every log_every = 5 steps
    assert result.step == 60 and [s for s, _ in result.losses] == list(range(5, 61, 5))
    assert np.mean(losses[-2:]) < 0.8 * losses[0]
    assert result.val_losses[-1][1] < result.val_losses[0][1]
    if precision == "bf16":  # the forward pass ran in bfloat16: not the float32 run's numbers, but as good
        fp32 = train(tiny_config(tmp_path / "fp32", steps=60), toy_bedrooms(80), progress=False, log=lambda m: None)
        assert losses != [v for _, v in fp32.losses]
        assert result.val_losses[-1][1] < 1.25 * fp32.val_losses[-1][1]
    out = tmp_path / "run"
    for name in (STATE_FILE, PRIOR_FILE, "config.yaml", "dataset_stats.json", "metrics.jsonl"):
        assert (out / name).exists(), name
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert rows[-1]["step"] == 60 and "val_loss_ema" in rows[-1] and "train_rooms_loss_ema" in rows[-1]
    prior = ScenePrior.load(out / PRIOR_FILE)
    assert prior.meta["step"] == 60
    scenes = prior.sample([l.floor for l in toy_bedrooms(2, seed=9)], num_steps=5,
                          generator=torch.Generator().manual_seed(0))
    assert scenes.labels.shape == (2, 12)


def test_the_paper_size_config_trains_a_step_on_the_cpu(tmp_path):
    cfg = load_config("experiments/pretrain_bedroom_paper.yaml", num_scenes=24, steps=1, batch_size=2,
                      val_scenes=2, device="cpu", out=str(tmp_path / "paper"))
    assert cfg.preset == "paper" and cfg.precision == "bf16"
    result = train(cfg, progress=False, log=lambda m: None)
    assert result.step == 1 and np.isfinite(result.losses[0][1])
    prior = ScenePrior.load(tmp_path / "paper" / PRIOR_FILE)
    assert prior.denoiser.config.num_layers == 8 and prior.denoiser.num_parameters() > 50e6


def test_interrupted_run_resumes_where_it_stopped(tmp_path):
    rooms = toy_bedrooms(40)
    quiet = dict(progress=False, log=lambda m: None)
    # uninterrupted reference
    ref = train(tiny_config(tmp_path / "a", steps=20, checkpoint_every=5, log_every=1), rooms, **quiet)
    # the same run, stopped at step 10 (as a kill after its checkpoint would), then started again
    cfg = tiny_config(tmp_path / "b", steps=20, checkpoint_every=5, log_every=1)
    first = train(cfg, rooms, max_steps=10, **quiet)
    assert first.step == 10
    state = torch.load(tmp_path / "b" / "run" / STATE_FILE, weights_only=True)
    assert state["step"] == 10
    second = train(cfg, rooms, **quiet)
    assert second.resumed_from == 10 and second.step == 20
    assert [s for s, _ in second.losses] == list(range(11, 21))
    resumed = [v for _, v in first.losses + second.losses]
    assert np.allclose(resumed, [v for _, v in ref.losses], rtol=1e-5, atol=1e-6)
    # a finished run started again does nothing more
    assert train(cfg, rooms, **quiet).losses == []
    # resuming with another model is refused with a hint
    with pytest.raises(ValueError, match="another output folder"):
        train(replace(cfg, model={"width": 64}), rooms, **quiet)
    # a run written in the dataset frame (before the room frame existed) is refused clearly, not half-loaded
    state["stats"]["translation_frame"] = "dataset"
    torch.save(state, tmp_path / "b" / "run" / STATE_FILE)
    with pytest.raises(ValueError, match="'dataset' frame"):
        train(cfg, rooms, **quiet)


def test_low_noise_fine_tune_trains_only_below_max_timestep(tmp_path, monkeypatch):
    from iarcs_env.schedule import NoiseSchedule

    seen = []
    original = NoiseSchedule.training_loss

    def spy(self, model_fn, x0, generator=None, t=None, **kw):
        if t is not None and torch.is_grad_enabled():
            seen.append(t.clone())
        return original(self, model_fn, x0, generator, t=t, **kw)

    monkeypatch.setattr(NoiseSchedule, "training_loss", spy)
    train(tiny_config(tmp_path, steps=5, max_timestep=40), toy_bedrooms(40), progress=False, log=lambda m: None)
    assert len(seen) == 5 and all(int(t.max()) < 40 for t in seen)
    with pytest.raises(ValueError, match="max_timestep"):
        tiny_config(tmp_path, max_timestep=1001)


def test_loss_feature_weights_weigh_the_floor_position_and_the_elevation():
    assert loss_feature_weights(PretrainConfig(), 30) is None  # the plain DDPM loss
    w = loss_feature_weights(PretrainConfig(translation_weight=3.0, elevation_weight=2.0), 30)
    assert w[:3].tolist() == [3.0, 2.0, 3.0] and (w[3:] == 1).all() and w.shape == (30,)
    with pytest.raises(ValueError, match="elevation_weight must be positive"):
        PretrainConfig(elevation_weight=0.0)


def test_out_of_bound_loss_measures_corners_behind_the_walls_and_pulls_objects_in():
    """The ``out_of_bound_weight`` loss on an L-shaped room: 0 on the data, the corners' distances behind the
    nearest wall when the prediction moves a nightstand into the missing corner, only below its timestep, and
    its gradient moves the nightstand back towards the room."""
    from iarcs_env.scene import floor_half_extents
    from tests.scene_factory import L_SHAPE, box, make_layout

    room = make_layout([box("double_bed", 1.0, 1.0, 0.9, 0.7), box("nightstand", 0.5, 3.0, 0.25, 0.25)],
                       floor=L_SHAPE).centred()  # the missing corner: x, z in [0, 2] after centring
    stats = stats_for_training([room], "bedroom", rotation_augment=True)
    stats.translation_frame = "room"
    batch = SceneTensors.from_layouts([room], BEDROOM.max_objects).batch(torch.arange(1))
    x0, _ = encode_batch(BEDROOM, stats, *batch)
    penalty = out_of_bound_excess(BEDROOM, stats, floor_half_extents([room.floor]), batch[4], weight=2.0,
                                  max_timestep=100)
    early = torch.tensor([10])
    assert float(penalty(x0, x0, early)) == pytest.approx(0.0, abs=1e-6)
    labels, trans, half, yaws = batch[:4]
    moved = trans.clone()
    moved[0, 1, [0, 2]] = torch.tensor([1.0, 1.0])  # the nightstand's centre 1 m inside the missing corner
    x_hat, _ = encode_batch(BEDROOM, stats, labels, moved, half, yaws, *batch[4:])
    # corners at 0.75 and 1.25 on both axes, each behind the nearer of the walls x = 0 and z = 0
    want = 2.0 * (0.75 + 0.75 + 0.75 + 1.25)
    assert float(penalty(x_hat, x0, early)) == pytest.approx(want, abs=0.03)  # boundary points every ~6 cm
    assert float(penalty(x_hat, x0, torch.tensor([100]))) == 0.0
    x_hat.requires_grad_(True)
    penalty(x_hat, x0, early).sum().backward()
    assert float(x_hat.grad[0, 1, 0]) > 0 and float(x_hat.grad[0, 1, 2]) > 0  # down the gradient: towards -x, -z
    assert float(x_hat.grad[0, 1, 3:].abs().max()) == 0.0  # nothing resized or turned
    with pytest.raises(ValueError, match="out_of_bound_weight"):
        PretrainConfig(out_of_bound_weight=-1.0)


def test_overlap_loss_measures_the_excess_over_the_data_and_pushes_objects_apart():
    """The ``overlap_weight`` loss: 0 on the data (tucked-in objects included), the extra overlap volume in
    m^3 when the prediction moves an object into another, only below ``overlap_max_timestep``, and never
    lowered by lifting, shrinking or turning objects."""
    from iarcs_env.geometry import box_overlap_volumes
    from iarcs_env.scene import floor_half_extents
    from tests.scene_factory import box, make_layout

    # a bed, and a nightstand tucked 0.1 m into its side (the data's own overlap: 0.1 x 0.4 x 0.5 m^3)
    room = make_layout([box("double_bed", 2.0, 1.2, 0.9, 1.0, hy=0.5), box("nightstand", 3.15, 0.5, 0.35, 0.2, hy=0.25),
                        box("wardrobe", 0.4, 2.6, 0.3, 0.35, yaw=math.pi / 2, hy=1.0)]).centred()
    stats = stats_for_training([room], "bedroom", rotation_augment=True)
    stats.translation_frame = "room"
    tensors = SceneTensors.from_layouts([room], BEDROOM.max_objects)
    batch = tensors.batch(torch.arange(1))
    x0, _ = encode_batch(BEDROOM, stats, *batch)
    extents = floor_half_extents([room.floor])
    penalty = overlap_excess(BEDROOM, stats, extents, weight=2.0, max_timestep=100)
    early = torch.tensor([10])
    assert float(penalty(x0, x0, early)) == 0.0
    # the prediction moves the wardrobe 0.5 m into the bed's corner (along x); the pair overlapped 0 before
    labels, trans, half, yaws = batch[:4]
    moved = trans.clone()
    moved[0, 2, 0] = trans[0, 0, 0] - 0.9 - 0.35 + 0.5  # wardrobe turned 90 degrees: 0.35 m half width along x
    moved[0, 2, 2] = trans[0, 0, 2] + 0.6
    x_hat, _ = encode_batch(BEDROOM, stats, labels, moved, half, yaws, *batch[4:])
    valid = labels != BEDROOM.empty_index
    exact = box_overlap_volumes(moved, half, yaws, valid)[0, 0, 2]
    assert float(exact) > 0.05
    assert float(penalty(x_hat, x0, early)) == pytest.approx(2.0 * float(exact), rel=1e-4)
    assert float(penalty(x_hat, x0, torch.tensor([100]))) == 0.0
    # lifting the wardrobe off the floor does not pay: heights count as in the data
    lifted = moved.clone()
    lifted[0, 2, 1] += 1.5
    x_lifted, _ = encode_batch(BEDROOM, stats, labels, lifted, half, yaws, *batch[4:])
    assert float(penalty(x_lifted, x0, early)) == pytest.approx(float(penalty(x_hat, x0, early)), rel=1e-6)
    # a step down its gradient moves the wardrobe out of the bed
    x_hat.requires_grad_(True)
    penalty(x_hat, x0, early).sum().backward()
    assert float(x_hat.grad[0, 2, 0]) > 0  # the wardrobe (left of the bed) is pushed towards -x
    assert float(x_hat.grad[0, 0, 0]) < 0  # the bed towards +x
    assert float(x_hat.grad[0, :3, 1].abs().max()) == 0.0  # and no object up or down,
    assert float(x_hat.grad[0, :3, 3:].abs().max()) == 0.0  # nor resized, turned or relabelled
    # the nightstand pushed 0.1 m deeper into the bed: charged the extra 0.1 x 0.4 x 0.5 m^3, unless the loss
    # spares the data's contact (the pair overlaps in the data); the wardrobe's new overlap is charged either way
    deeper = moved.clone()
    deeper[0, 1, 0] -= 0.1
    x_deeper, _ = encode_batch(BEDROOM, stats, labels, deeper, half, yaws, *batch[4:])
    spared = overlap_excess(BEDROOM, stats, extents, weight=2.0, max_timestep=100, spare_contact=True)
    assert float(penalty(x_deeper, x0, early)) == pytest.approx(2.0 * (float(exact) + 0.02), rel=1e-3)
    assert float(spared(x_deeper, x0, early)) == pytest.approx(2.0 * float(exact), rel=1e-4)
    # the wardrobe's bounds stand 0.35 m from the bed's along x in the data (0.1 m along z): spared as contact
    # within a 0.4 m gap, charged within 0.3 m
    near = {gap: overlap_excess(BEDROOM, stats, extents, weight=2.0, max_timestep=100, spare_contact=True,
                                contact_gap=gap) for gap in (0.3, 0.4)}
    assert float(near[0.3](x_hat.detach(), x0, early)) == pytest.approx(2.0 * float(exact), rel=1e-4)
    assert float(near[0.4](x_hat.detach(), x0, early)) == 0.0
    # charged only beyond a contact volume
    beyond = overlap_excess(BEDROOM, stats, extents, weight=2.0, max_timestep=100, spare_contact=True,
                            contact_gap=0.4, contact_volume=0.02)
    assert float(beyond(x_hat.detach(), x0, early)) == pytest.approx(2.0 * (float(exact) - 0.02), rel=1e-4)
    with pytest.raises(ValueError, match="overlap_weight"):
        PretrainConfig(overlap_weight=-1)
    with pytest.raises(ValueError, match="overlap_contact_gap"):
        PretrainConfig(overlap_contact_gap=-0.1)


def test_pretraining_adds_the_overlap_loss_when_asked(tmp_path):
    quiet = dict(progress=False, log=lambda m: None)
    rooms = toy_bedrooms(40)
    plain = train(tiny_config(tmp_path / "plain", steps=1, log_every=1), rooms, **quiet)
    overlap = train(tiny_config(tmp_path / "overlap", steps=1, log_every=1, overlap_weight=1.0,
                                overlap_max_timestep=1000), rooms, **quiet)
    spared = train(tiny_config(tmp_path / "spared", steps=1, log_every=1, overlap_weight=1.0,
                               overlap_max_timestep=1000, overlap_spares_contact=True), rooms, **quiet)
    # the same first batch, noise and network: the overlap term of a random network's x0_hat adds to the loss,
    # less of it where the pairs the toy rooms put in contact (a nightstand into its bed) are spared
    assert math.isfinite(overlap.losses[0][1]) and overlap.losses[0][1] > plain.losses[0][1] + 0.01
    assert plain.losses[0][1] + 0.01 < spared.losses[0][1] < overlap.losses[0][1] - 1e-4


def test_fine_tuning_starts_from_the_init_prior(tmp_path):
    quiet = dict(progress=False, log=lambda m: None)
    base = train(tiny_config(tmp_path / "base", steps=60), toy_bedrooms(80), **quiet)
    init = ScenePrior.load(tmp_path / "base" / "run" / PRIOR_FILE)
    # other rooms (another seed, larger): fine-tuning keeps the init's feature scaling, takes the new rooms'
    # class and count statistics, and starts at the init's validation loss, not at a random network's
    other = [l.rotated(math.pi / 2) for l in toy_bedrooms(80, seed=5)]
    tuned_cfg = tiny_config(tmp_path / "tuned", steps=1, eval_every=1, log_every=1, lr=1e-12, warmup_steps=0,
                            init_from=str(tmp_path / "base" / "run" / PRIOR_FILE))
    tuned = train(tuned_cfg, other, **quiet)
    scratch = train(tiny_config(tmp_path / "scratch", steps=1, eval_every=1, log_every=1), other, **quiet)
    stats = json.loads((tmp_path / "tuned" / "run" / "dataset_stats.json").read_text())
    assert stats["bounds_translations"] == pytest.approx(init.stats.bounds_translations)
    assert stats["bounds_sizes"] == pytest.approx(init.stats.bounds_sizes)
    assert tuned.val_losses[0][1] < 0.7 * scratch.val_losses[0][1]
    assert tuned.val_losses[0][1] == pytest.approx(base.val_losses[-1][1], rel=0.5)
    # a prior of another room or architecture is refused with what to change
    with pytest.raises(ValueError, match="another architecture"):
        train(tiny_config(tmp_path / "bad", model={"width": 64}, init_from=tuned_cfg.init_from), other, **quiet)
    with pytest.raises(ValueError, match="same room type"):
        train(tiny_config(tmp_path / "bad2", room="livingroom", init_from=tuned_cfg.init_from), [], **quiet)
    with pytest.raises(ValueError, match="predicts 'epsilon'.*set prediction_type: epsilon"):
        train(tiny_config(tmp_path / "bad3", prediction_type="sample", init_from=tuned_cfg.init_from), [], **quiet)


def test_cli_pretrain_and_sample(tmp_path, capsys):
    from experiments.cli import main

    data = save_layouts(toy_bedrooms(30), tmp_path / "rooms.json")
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(f"room: bedroom\ndataset: {data}\npreset: tiny\nbatch_size: 8\nsteps: 50\n"
                   f"checkpoint_every: 2\nlog_every: 2\neval_every: 2\nval_scenes: 3\ntensorboard: false\n")
    run = tmp_path / "run"
    assert main(["pretrain", "--config", str(cfg), "--out", str(run), "--steps", "4"]) == 0
    assert "step 4/4" in capsys.readouterr().out
    assert main(["pretrain", "--config", str(cfg), "--out", str(run), "--steps", "4", "--no-resume"]) == 2
    assert "drop --no-resume" in capsys.readouterr().err
    assert main(["pretrain", "--config", str(cfg), "--out", str(run), "--steps", "6", "--stop-at", "5"]) == 0
    assert "step 5/6" in capsys.readouterr().out  # stopped as if interrupted, with the 6-step schedule
    assert main(["pretrain", "--config", str(cfg), "--out", str(run), "--stop-at", "0"]) == 2

    out = tmp_path / "samples.json"
    args = ["sample", "--room", "bedroom", "--checkpoint", str(run / PRIOR_FILE), "--steps", "3"]
    assert main(args + ["--floors", str(data), "--num-scenes", "5", "--out", str(out)]) == 0
    scenes = json.loads(out.read_text())["scenes"]
    assert len(scenes) == 5
    src = json.loads(data.read_text())["scenes"]
    assert scenes[2]["floor"] == src[2]["floor"]  # room for room, in the floor's own frame
    assert main(args + ["--floors", str(data), "--num-scenes", "99", "--out", str(out)]) == 2
    assert "--num-scenes 30 or fewer" in capsys.readouterr().err
    assert main(args[:2] + ["livingroom"] + args[3:] + ["--out", str(out)]) == 2
    assert "--room bedroom" in capsys.readouterr().err
    assert main(["sample", "--room", "diningroom", "--num-scenes", "2", "--steps", "3", "--out", str(out)]) == 0
    assert len(json.loads(out.read_text())["scenes"]) == 2  # the shipped dining-room prior
    assert main(args + ["--num-scenes", "0", "--out", str(out)]) == 2


def test_the_fast_training_step_matches_a_plain_reference_step(tmp_path):
    """Three steps of :func:`training_step` (the PointNet max-pool without its (B, P, F) activation, the
    cross-attention without the floor tokens' keys and values, the x0-hat
    losses on the low-noise scenes only, fused AdamW, a foreach EMA) against plain steps written out here
    (the plain layers, the losses on every scene times the mask, torch's default AdamW, a loop over the EMA
    weights), from the same weights on the same batches: the same losses, weights and EMA weights."""
    from unittest import mock

    import agents.pretrain as pre
    import agents.x0_losses as x0_losses
    from agents.denoiser import Attention, SceneDenoiser
    from agents.pointnet import PointNetEncoder
    from iarcs_env.schedule import NoiseSchedule

    rooms = toy_bedrooms(40)
    cfg = tiny_config(tmp_path, preset="small", batch_size=24, overlap_weight=1.0, overlap_max_timestep=500,
                      out_of_bound_weight=1.0, out_of_bound_max_timestep=500, elevation_weight=10.0)
    stats = replace(stats_for_training(rooms, "bedroom", True), translation_frame="room")
    data = SceneTensors.from_layouts(rooms, BEDROOM.max_objects)
    weights = loss_feature_weights(cfg, BEDROOM.feature_dim)
    schedule = NoiseSchedule()
    torch.manual_seed(0)
    nets = [SceneDenoiser(cfg.denoiser_config(), BEDROOM.feature_dim) for _ in range(2)]
    nets[1].load_state_dict(nets[0].state_dict())
    for net in nets:
        net.set_metric_scale(stats)
    emas = [copy.deepcopy(net).requires_grad_(False) for net in nets]
    fast_opt = torch.optim.AdamW(nets[0].parameters(), lr=1e-3, fused=True)
    plain_opt = torch.optim.AdamW(nets[1].parameters(), lr=1e-3)
    batches = [pre.draw_batch(data, cfg, BEDROOM, stats, torch.Generator().manual_seed(i), 24) for i in range(3)]
    assert all(int((b.t < 500).sum()) not in (0, 24) for b in batches)  # some scenes with the x0-hat losses, some not

    for batch in batches:
        fast, _ = pre.training_step(nets[0], nets[0], emas[0], fast_opt, schedule, cfg, BEDROOM, stats, weights,
                                    lambda: batch, 1e-3, 0.9)
        with mock.patch.object(PointNetEncoder, "encode", PointNetEncoder.encode_reference), \
                mock.patch.object(Attention, "forward", Attention.forward_reference), \
                mock.patch.object(x0_losses, "on_rows", lambda mask, per_scene, *scenes: per_scene(*scenes) * mask):
            plain = pre.batch_loss(nets[1], schedule, batch, cfg, BEDROOM, stats, weights).mean()
        plain_opt.zero_grad()
        plain.backward()
        torch.nn.utils.clip_grad_norm_(nets[1].parameters(), cfg.grad_clip)
        plain_opt.step()
        with torch.no_grad():
            for pe, p in zip(emas[1].parameters(), nets[1].parameters()):
                pe.copy_(0.9 * pe + 0.1 * p)
        assert float(fast) == pytest.approx(float(plain.detach()), rel=1e-5)
    for a, b in zip(list(nets[0].parameters()) + list(emas[0].parameters()),
                    list(nets[1].parameters()) + list(emas[1].parameters())):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6)


def test_a_failed_compile_falls_back_to_eager_training(tmp_path, monkeypatch):
    """``compile: true`` where the compiler breaks (here: a compiled model that raises as a missing backend would):
    one log line with the reason, then the same run as without it."""
    def broken_compile(model, **kw):
        def call(*args, **kwargs):
            raise RuntimeError("backend 'inductor' failed: no C++ compiler")
        return call

    monkeypatch.setattr(torch, "compile", broken_compile)
    lines, rooms = [], toy_bedrooms(40)
    result = train(tiny_config(tmp_path / "c", steps=5, compile=True), rooms, progress=False, log=lines.append)
    plain = train(tiny_config(tmp_path / "p", steps=5), rooms, progress=False, log=lambda m: None)
    assert any(line.startswith("torch.compile failed (RuntimeError: backend 'inductor' failed") for line in lines)
    assert result.step == 5 and result.losses == plain.losses


def test_a_time_budget_stops_the_run_with_a_checkpoint(tmp_path):
    cfg = tiny_config(tmp_path, steps=100_000, lr_schedule="constant", checkpoint_every=1000, log_every=1000)
    result = train(cfg, toy_bedrooms(40), progress=False, log=lambda m: None, time_budget=3.0)
    assert result.stopped_by_deadline and 0 < result.step < 100_000 and result.seconds < 3.0 + 2.0
    state = torch.load(tmp_path / "run" / STATE_FILE, weights_only=True)
    assert state["step"] == result.step and ScenePrior.load(tmp_path / "run" / PRIOR_FILE).meta["step"] == result.step
    assert lr_at(50_000, cfg) == cfg.lr  # constant after the warm-up
    # a new run continues it: weights, EMA and optimizer state
    more = train(tiny_config(tmp_path / "more", steps=3, init_from=str(tmp_path / "run")), toy_bedrooms(40),
                 progress=False, log=lambda m: None)
    assert more.step == 3 and more.resumed_from == 0
