"""``iarcs evaluate``: JSON + Markdown reports, issue renders, clear user errors."""

import argparse
import json

import pytest

from experiments.commands import evaluate as ev
from iarcs_env.datasets import save_layouts
from iarcs_env.metrics import HEADLINE
from scene_factory import box, make_layout, random_layouts


def run(argv):
    parser = argparse.ArgumentParser(prog="iarcs")
    sub = parser.add_subparsers(dest="command")
    ev.register(sub)
    args = parser.parse_args(["evaluate", *argv])
    return args.func(args)


@pytest.fixture
def files(tmp_path):
    scenes = random_layouts(12, seed=0, max_objects=5)
    scenes.append(make_layout([box("wardrobe", 1.0, 1.5, 0.5, 0.3), box("cabinet", 1.8, 1.5, 0.5, 0.3)], id="clash"))
    save_layouts(scenes, tmp_path / "gen.json")
    save_layouts(random_layouts(12, seed=1, max_objects=5), tmp_path / "real.json")
    return tmp_path


def test_evaluate_writes_json_markdown_and_issue_renders(files, capsys):
    out = files / "report" / "gen.json"
    assert run(["--scenes", str(files / "gen.json"), "--out", str(out), "--render-issues", str(files / "issues"),
                "--features", "none", "--reference", str(files / "real.json")]) == 0
    report = json.loads(out.read_text())
    for key in HEADLINE:
        assert 0.0 <= report[key] <= 1.0
    assert report["feature_extractor"].startswith("none") and "FID" not in report
    assert "KL_class" in report and report["n_scenes"] == 13
    clash = next(s for s in report["per_scene"] if s["id"] == "clash")
    assert clash["colliding"] == [0, 1]
    md = out.with_suffix(".md").read_text()
    assert "| Col_obj % ↓ |" in md and "feature extractor" in md
    pngs = list((files / "issues").glob("*.png"))
    assert pngs and any("clash" in p.name for p in pngs)
    assert "Col_obj" in capsys.readouterr().out


def test_evaluate_with_the_project_cnn_names_it(files, monkeypatch):
    monkeypatch.setenv("IARCS_CACHE_DIR", str(files / "cache"))
    out = files / "gen.json.report.json"
    assert run(["--scenes", str(files / "gen.json"), "--reference", str(files / "real.json"), "--out", str(out),
                "--render-size", "32"]) == 0
    report = json.loads(out.read_text())
    assert report["feature_extractor"].startswith("render-cnn:")
    assert {"FID", "KID", "SCA"} <= set(report)


def test_user_errors_are_clear(files, capsys):
    from experiments.cli import main

    assert main(["evaluate", "--scenes", str(files / "missing.json"), "--out", str(files / "r.json")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["evaluate", "--scenes", str(files / "gen.json"), "--out", str(files / "r.txt")]) == 2
    assert ".json" in capsys.readouterr().err
    assert main(["evaluate", "--scenes", str(files / "gen.json"), "--out", str(files / "r.json"),
                 "--features", "inception", "--reference", str(files / "real.json")]) == 2
    assert "--features" in capsys.readouterr().err
