import json
import subprocess
import sys

import pytest

from experiments.cli import main
from iarcs_env.datasets import load_layouts, save_layouts
from conftest import L_SHAPE, REPO, make_layout

OBJECTS = [("double_bed", (2.0, 0.4, 1.0), (0.9, 0.4, 1.05), 1.5708),
           ("nightstand", (0.3, 0.25, 2.4), (0.25, 0.25, 0.2), -1.5708)]


@pytest.fixture
def scenes(tmp_path):
    layouts = [make_layout(OBJECTS, id="a"), make_layout(OBJECTS[1:], floor=L_SHAPE, id="b")]
    return save_layouts(layouts, tmp_path / "scenes.json")


def test_generate_writes_valid_scenes(tmp_path, capsys):
    out = tmp_path / "gen.json"
    assert main(["data", "generate", "--room", "bedroom", "--num-scenes", "6", "--seed", "3", "--out", str(out)]) == 0
    layouts = load_layouts(out)
    assert len(layouts) == 6 and all(l.room_type == "bedroom" and len(l) <= 12 for l in layouts)
    assert "wrote 6 bedrooms" in capsys.readouterr().out


def test_convert_round_trip_and_render_and_stats(tmp_path, scenes, capsys):
    assert main(["data", "convert", "--in", str(scenes), "--out", str(tmp_path / "atiss")]) == 0
    assert len(list((tmp_path / "atiss").glob("*/boxes.npz"))) == 2
    assert main(["data", "convert", "--in", str(tmp_path / "atiss"), "--out", str(tmp_path / "back.json")]) == 0
    a = json.loads(scenes.read_text())["scenes"]
    assert json.loads((tmp_path / "back.json").read_text())["scenes"] == a

    assert main(["data", "render", "--in", str(scenes), "--out", str(tmp_path / "png"), "--limit", "1"]) == 0
    assert sorted(p.name for p in (tmp_path / "png").iterdir()) == ["00000.png", "overview.png"]

    capsys.readouterr()
    assert main(["data", "stats", "--in", str(scenes), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["scenes"] == 2 and s["objects"] == 3 and s["class_frequencies"]["nightstand"] == pytest.approx(2 / 3)
    assert s["room_area_m2"]["median"] == pytest.approx(12.0) and s["non_rectangular_fraction"] == 0.5


@pytest.mark.parametrize("argv, message", [
    (["data", "stats", "--in", "nowhere.json"], "no such layout file"),
    (["data", "render", "--in", "nowhere.json", "--out", "x", "--limit", "0"], "--limit must be a positive"),
    (["data", "generate", "--room", "garage", "--num-scenes", "3", "--out", "x.json"], "unknown room type"),
    (["data", "generate", "--room", "bedroom", "--num-scenes", "-1", "--out", "x.json"], "--num-scenes must be"),
])
def test_bad_input_gives_a_message_not_a_traceback(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_convert_refuses_json_to_json_and_plain_folders(tmp_path, scenes, capsys):
    assert main(["data", "convert", "--in", str(scenes), "--out", str(tmp_path / "x.json")]) == 2
    (tmp_path / "plain").mkdir()
    assert main(["data", "convert", "--in", str(tmp_path / "plain"), "--out", str(tmp_path / "y.json")]) == 2
    err = capsys.readouterr().err
    assert "give a folder as --out" in err and "not an ATISS preprocessed folder" in err


def test_console_script_runs_as_a_process(tmp_path, scenes):
    exe = REPO / ".venv" / "bin" / "iarcs"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "experiments.cli"]
    done = subprocess.run(cmd + ["data", "stats", "--in", str(scenes)], capture_output=True, text=True, cwd=REPO)
    assert done.returncode == 0 and "2 scenes" in done.stdout
    bad = subprocess.run(cmd + ["data", "stats", "--in", str(tmp_path / "none.json")], capture_output=True, text=True, cwd=REPO)
    assert bad.returncode == 2 and "no such layout file" in bad.stderr
