"""Issue 25: COLMAP's cross-check on the pairs the model chooses (--pairing model; long captures by default)."""

import json

import pycolmap
import pytest

from ffrecon.cli import main
from ffrecon.geometry.metrics import pose_errors
from ffrecon.geometry.overlap import overlap_graph
from ffrecon.pipeline import RunOptions, run
from ffrecon.sfm.crosscheck import mapping
from ffrecon.sfm.crosscheck.mapping import MapperRun
from ffrecon.sfm.crosscheck.matching import resolve_pairing
from ffrecon.sfm.crosscheck.options import ColmapOptions, PairingMode
from ffrecon.sfm.refine import run as refine
from ffrecon.sfm.refine.options import RefineOptions
from ffrecon.splat.stage import SplatOptions
from ffrecon.synthetic.scene import load_scene


def test_auto_pairing_takes_the_models_pairs_past_the_exhaustive_limit():
    options = ColmapOptions(exhaustive_max_images=10)
    assert resolve_pairing(options, 10, model=True) is PairingMode.EXHAUSTIVE
    assert resolve_pairing(options, 11, model=True) is PairingMode.MODEL
    assert resolve_pairing(options, 11, model=False) is PairingMode.SEQUENTIAL


def test_crosscheck_on_model_pairs_matches_fewer_pairs_and_registers_every_frame(tmp_path, demo12, monkeypatch):
    """The 12-frame demo: the model's pairs are a subset of all 66, COLMAP still registers every frame and its
    cameras stay at the exhaustive run's accuracy against the truth; the cross-check then runs after the model,
    and the refinement takes the overlap graph it made instead of making it again."""
    made = []
    monkeypatch.setattr(refine, "overlap_graph", lambda *a, **k: made.append(a) or overlap_graph(*a, **k))
    runs = {}
    for pairing in (PairingMode.EXHAUSTIVE, PairingMode.MODEL):
        options = RunOptions(
            colmap=ColmapOptions(pairing=pairing),
            refine=RefineOptions(enabled=pairing is PairingMode.MODEL),
            splat=SplatOptions(enabled=False),
        )
        runs[pairing] = run(demo12.images, tmp_path / pairing.value, demo12.model, options)
    truth = load_scene(demo12.scene_dir)
    exhaustive, model = runs[PairingMode.EXHAUSTIVE].colmap, runs[PairingMode.MODEL].colmap
    assert model.pairing is PairingMode.MODEL and model.registered.all()
    assert model.features.num_pairs_matched < exhaustive.features.num_pairs_matched == 66
    errors = [pose_errors(r.cam_from_world, truth.cam_from_world) for r in (exhaustive, model)]
    assert errors[1].auc[5] >= errors[0].auc[5] - 0.02 and errors[1].auc[5] > 0.95
    report = json.loads((tmp_path / "model" / "report.json").read_text())
    assert report["colmap"]["pairing"] == "model"
    assert report["timings"]["colmap_matching"]["concurrent_with"] is None, "it read the model's result: not beside it"
    listed = (tmp_path / "model" / "crosscheck" / "model_pairs.txt").read_text().split("\n")
    assert len([line for line in listed if line]) == model.features.num_pairs_matched
    assert pycolmap.Reconstruction(tmp_path / "model" / "crosscheck" / "sparse" / "0").num_reg_images() == 12
    assert len(model.model_overlap.pairs) == model.features.num_pairs_matched
    assert made == [] and runs[PairingMode.MODEL].refine.registered.all()  # the cross-check's graph, reused


def test_model_pairing_without_a_model_says_so(tmp_path, demo12, capsys):
    code = main(["run", str(demo12.images), "-o", str(tmp_path / "out"), "--pairing", "model", "-q"])
    assert code == 2 and "--pairing model" in capsys.readouterr().err


@pytest.mark.parametrize(("num_images", "order"), [(399, ["incremental", "global"]), (400, ["global", "incremental"])])
def test_auto_mapping_takes_the_global_mapper_first_on_long_captures(tmp_path, monkeypatch, num_images, order):
    """Past ``global_first_images`` the global mapper runs first; the other runs only when it leaves images out."""
    tried = []

    def fake_mapper(kind, db_path, image_dir, work_dir, options, n):
        tried.append(kind.value)
        registered = n if len(tried) == 2 else n - 1  # the first leaves one image out, so both run
        return [], MapperRun(kind, 1, registered, 100, 0.5, 0, 1.0)

    monkeypatch.setattr(mapping, "_run_mapper", fake_mapper)
    mapping.map_images(tmp_path / "db", tmp_path, tmp_path / "work", ColmapOptions(), num_images)
    assert tried == order
