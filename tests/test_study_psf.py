"""The study's PSF choice: it reaches the renderer, and the cache keeps the PSFs apart."""

import pytest
from click.testing import CliRunner

# imported before render_image is patched below: they bind it when first imported, and one
# first imported under the patch would keep the fake for every later test of the process
import zoomcalib.render.dataset  # noqa: F401
import zoomcalib.render.image as render_image_module
import zoomcalib.render.sweep  # noqa: F401
import zoomcalib.study.run as study_run
from zoomcalib.cli import main
from zoomcalib.study.engine import task_fingerprint, task_seed
from zoomcalib.study.paper import StudyConfig, detection_task
from zoomcalib.study.run import detection_tasks

SMALL = {"zooms": (0.0, 0.5), "noise_dn": (2.0,), "seeds": 2, "views": 3}


class _Stop(Exception):
    """Raised by the stand-ins below once they have seen what they were given."""

    def __init__(self, seen):
        super().__init__("stopped")
        self.seen = seen


def _fingerprints(config: StudyConfig) -> dict[str, str]:
    return {t.key: task_fingerprint(t.fn, t.kwargs, task_seed(config.seed, t.key))
            for t in detection_tasks(config)}


def test_unknown_psf_is_refused():
    with pytest.raises(ValueError, match="psf must be one of"):
        StudyConfig(psf="gausian")


def test_default_study_keeps_its_task_fingerprints():
    """Caches written before the PSF option existed stay valid for the Gaussian study: the
    arguments below are written out as the tasks had them then."""
    config = StudyConfig(**SMALL)
    fig6_zoom = 0.5  # the middle step of the two
    for t in detection_tasks(config):
        z = t.kwargs["zoom"]
        before = {"lens": "laikin-10x", "zoom": z, "noise_dn": 2.0, "views": 3,
                  "pattern": "chessboard:9x6:25", "blur_px": 0.7,
                  "detectors": ["classic", "model"], "backends": ["opencv", "bundle"],
                  "keep_errors": t.key.endswith("set00") and z == fig6_zoom}
        seed = task_seed(0, t.key)
        assert task_fingerprint(t.fn, t.kwargs, seed) == task_fingerprint(t.fn, before, seed)


@pytest.mark.parametrize("psf", ["airy", "halo", "elliptical"])
def test_another_psf_never_reuses_a_cached_task(psf):
    gauss = _fingerprints(StudyConfig(**SMALL))
    other = _fingerprints(StudyConfig(**SMALL, psf=psf))
    assert other.keys() == gauss.keys()  # same keys, so the same seeds: paired comparison
    assert all(other[k] != gauss[k] for k in gauss)
    assert len(set(other.values())) == len(other)


@pytest.mark.parametrize("psf", ["gaussian", "elliptical"])
def test_detection_task_renders_with_the_study_psf(monkeypatch, psf):
    def fake_render(target, mapping, R, t, sensor, optics, radiometry, rng, *a, **k):
        raise _Stop(optics)

    monkeypatch.setattr(render_image_module, "render_image", fake_render)
    (task,) = [t for t in detection_tasks(StudyConfig(**SMALL, psf=psf))
               if t.key.endswith("set01") and t.kwargs["zoom"] == 0.0]
    with pytest.raises(_Stop) as stop:
        detection_task(**task.kwargs, seed=1)
    assert stop.value.seen.psf == psf
    assert stop.value.seen.blur_px == 0.7


@pytest.mark.parametrize(("args", "expected"), [([], "gaussian"), (["--psf", "airy"], "airy")])
def test_cli_passes_the_psf_to_the_study(monkeypatch, tmp_path, args, expected):
    def fake_run_study(config, out, **kwargs):
        raise _Stop(config)

    monkeypatch.setattr(study_run, "run_study", fake_run_study)
    res = CliRunner().invoke(main, ["study", "--quick", *args, "--out", str(tmp_path / "s")])
    assert isinstance(res.exception, _Stop), res.output
    assert res.exception.seen.psf == expected


def test_cli_refuses_an_unknown_psf(tmp_path):
    res = CliRunner().invoke(main, ["study", "--psf", "box", "--out", str(tmp_path / "s")])
    assert res.exit_code == 2
    assert "box" in res.output


def test_a_binned_sensor_keeps_the_field_of_view_and_a_bad_binning_is_refused():
    from zoomcalib.camera import DEFAULT_SENSOR
    from zoomcalib.study.paper import DetectionSetting

    setting = DetectionSetting("laikin-10x", 0.0, 2.0, 8, "chessboard:9x6:25", 0.7, ["model"],
                               ["opencv"], binning=4)
    binned = setting.sensor()
    assert (binned.width_px, binned.height_px) == (320, 240)
    assert binned.width_px * binned.pixel_pitch_mm == pytest.approx(
        DEFAULT_SENSOR.width_px * DEFAULT_SENSOR.pixel_pitch_mm, rel=1e-12)
    assert setting.__class__(**{**setting.__dict__, "binning": 1}).sensor() == DEFAULT_SENSOR
    for bad in (0, 7, 2.0):
        with pytest.raises(ValueError, match="binning must be a whole divisor"):
            DetectionSetting(**{**setting.__dict__, "binning": bad}).sensor()
