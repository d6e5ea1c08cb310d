"""The plotted run report (vigs_core.eval.report_html): every figure the page names exists and is drawn, figures
that need missing data are left out saying why, `vigs eval --html` overlays several runs, and the page loads in a
real headless Chromium (every image decoded, a non-blank screenshot). Synthetic run folders keep it to seconds."""
import html
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vigs_core.eval import evaluate_trajectory
from vigs_core.eval.report_html import load_run, write_run_report
from vigs_core.io import write_tum
from vigs_core.types import Trajectory

RATE, N, KF_EVERY = 20.0, 200, 10
ALL_FIGURES = {"trajectory.png", "ate.png", "keyframes.png", "vio_states.png", "stage_times.png"}


def groundtruth() -> Trajectory:
    """A 10 s loop in 3D at the frame times (identity orientations)."""
    t = np.arange(N) / RATE
    position = np.column_stack((np.cos(0.6 * t), np.sin(0.6 * t), 0.2 * np.sin(1.1 * t)))
    return Trajectory(1_000_000_000 + (t * 1e9).astype(np.int64), position, np.tile([1.0, 0, 0, 0], (N, 1)))


def write_run(folder: Path, gt: Trajectory, vio: bool = True, loops: list | None = None, scale: float = 0.5,
              bump_m: float = 0.05) -> Path:
    """A ``vigs run``-like output folder: the ground truth in another Sim(3) frame with a growing error of up to
    ``bump_m``, keyframes every 10th frame, velocities, and a report.json with timings, loops and (``vio``) the
    visual-inertial state."""
    folder.mkdir(parents=True, exist_ok=True)
    rot = Rotation.from_rotvec([0.3, -0.2, 1.0])
    drift = bump_m * np.linspace(0, 1, N)[:, None] * np.array([1.0, -0.5, 0.3])
    est = Trajectory(gt.t_ns, scale * rot.apply(gt.position + drift) + [2.0, -1.0, 0.5], gt.quat_wxyz)
    write_tum(folder / "trajectory.txt", est)
    write_tum(folder / "keyframes.txt", Trajectory(est.t_ns[::KF_EVERY], est.position[::KF_EVERY],
                                                   est.quat_wxyz[::KF_EVERY]))
    t_kf = gt.t_ns[::KF_EVERY].tolist()
    velocity = np.gradient(gt.position, axis=0) * RATE
    np.savetxt(folder / "velocity.txt", np.column_stack((gt.t_s, velocity)), fmt="%.9f")
    report = {"sequence": "synthetic", "frames": N, "frames_posed": N, "keyframes": len(t_kf),
              "frames_per_s": 25.0, "timings_s": {"flow": 4.0, "ba": 2.0, "tracking": 0.5},
              "loop": {"loops_found": len(loops or []), "accepted_pairs": loops or []}}
    if vio:
        k = len(t_kf)
        report["vio"] = {"scale_history": [{"t_ns": t_kf[5], "stage": "aligned", "scale": 0.4},
                                           {"t_ns": t_kf[15], "stage": "scale_check", "scale": 1.01}],
                         "keyframe_states": {"t_ns": t_kf, "velocity": velocity[::KF_EVERY].tolist(),
                                             "bias_gyro": np.linspace([0, 0.01, 0.02], [0.001, 0.012, 0.02], k).tolist(),
                                             "bias_acc": np.linspace([0, 0.1, 0.0], [0.05, 0.12, -0.03], k).tolist()}}
    (folder / "report.json").write_text(json.dumps(report))
    return folder


def page_figures(page: Path) -> list[Path]:
    """The image files the page's <img> elements point at."""
    return [page.parent / src for src in re.findall(r'<img src="([^"]+)"', page.read_text())]


def omitted(page: Path) -> list[str]:
    return re.findall(r'<p class="omitted">([^<]*)</p>', page.read_text())


def assert_drawn_png(path: Path) -> None:
    """A PNG that decodes, is figure-sized and carries a drawing: many grey levels, not one flat colour."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert image is not None and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", path
    assert image.shape[1] >= 800 and image.shape[0] >= 150, (path, image.shape)
    assert image.std() > 10 and len(np.unique(image.reshape(-1, 3) @ [1 << 16, 1 << 8, 1])) > 50, path


@pytest.fixture
def full_report(tmp_path) -> Path:
    """report.html of a run folder with the data of every figure (ground truth, VIO state, a loop closure)."""
    gt = groundtruth()
    return write_run_report(write_run(tmp_path / "run", gt, loops=[[2, 17]]), gt)


def test_run_report_names_every_figure_and_each_is_a_drawn_png(full_report):
    page, run = full_report, full_report.parent
    assert page.name == "report.html"
    figures = page_figures(page)
    assert {f.name for f in figures} == ALL_FIGURES and not omitted(page)
    assert {f.name for f in (run / "report_figures").iterdir()} == ALL_FIGURES   # nothing unreferenced
    for figure in figures:
        assert_drawn_png(figure)
    text = page.read_text()
    # the table shows the numbers vigs eval computes; the captions say what is drawn
    metrics = evaluate_trajectory(groundtruth(), load_run(run / "trajectory.txt").trajectory)
    assert 0.005 < metrics["ate_rmse"] < 0.05 and metrics["scale"] == pytest.approx(2.0, rel=0.05)
    assert f"<td>{metrics['ate_rmse']:.4g}</td>" in text and f"<td>{metrics['scale']:.4g}</td>" in text
    assert "coloured by the translation error" in text and "synthetic: 1 loop closures accepted" in text


def test_figures_without_their_data_are_left_out_saying_why(tmp_path):
    gt = groundtruth()
    run = write_run(tmp_path / "run", gt, vio=False)
    write_run_report(run, gt)
    assert (run / "report_figures" / "ate.png").is_file()
    page = write_run_report(run)   # no ground truth: the ATE figure goes, and its stale file with it
    names = {f.name for f in page_figures(page)}
    assert names == {"trajectory.png", "keyframes.png", "stage_times.png"}
    assert {f.name for f in (run / "report_figures").iterdir()} == names
    reasons = omitted(page)
    assert any(r.startswith("ATE over time: left out: no ground truth") for r in reasons), reasons
    assert any(r.startswith("Scale, biases and speed: left out: no visual-inertial state") for r in reasons)
    assert "No ground truth: each estimate in its own world frame" in page.read_text()
    assert "<td>-</td>" in page.read_text()   # no accuracy in the table

    # a bare trajectory file: only what it holds is drawn
    bare = tmp_path / "bare" / "est.txt"
    bare.parent.mkdir()
    shutil.copy(run / "trajectory.txt", bare)
    from vigs_core.eval.report_html import write_report

    page = write_report([load_run(bare)], tmp_path / "bare.html", gt)
    assert {f.name for f in page_figures(page)} == {"trajectory.png", "ate.png"}
    reasons = omitted(page)
    assert any("no keyframes.txt beside the estimate" in r for r in reasons)
    assert any("Time per frame by stage: left out: no report.json" in r for r in reasons)


def test_a_run_too_short_for_a_keyframe_is_still_reported(tmp_path):
    """vigs run writes empty keyframes.txt and velocity.txt when no keyframe was made: the page is written without
    the keyframe figure, saying why."""
    gt = groundtruth()
    run = write_run(tmp_path / "run", gt, vio=False)
    (run / "keyframes.txt").write_text("# timestamp[s] tx ty tz qx qy qz qw\n")
    (run / "velocity.txt").write_text("")
    page = write_run_report(run, gt)
    assert "keyframes.png" not in {f.name for f in page_figures(page)}
    assert any("keyframes" in r for r in omitted(page)), omitted(page)


def test_vigs_eval_html_overlays_several_runs_and_keeps_the_single_run_output(tmp_path):
    gt = groundtruth()
    gt_file = tmp_path / "gt.txt"
    write_tum(gt_file, gt)
    a = write_run(tmp_path / "a", gt, bump_m=0.02) / "trajectory.txt"
    b = write_run(tmp_path / "b", gt, vio=False, loops=[[1, 12]], bump_m=0.2) / "trajectory.txt"
    eval_cmd = [sys.executable, "-m", "vigs_cli.main", "eval", str(gt_file)]

    single = subprocess.run(eval_cmd + [str(a)], capture_output=True, text=True, timeout=120)
    with_html = subprocess.run(eval_cmd + [str(a), "--html", str(tmp_path / "one.html")], capture_output=True,
                               text=True, timeout=120)
    assert single.returncode == with_html.returncode == 0, with_html.stderr
    assert with_html.stdout == single.stdout and single.stdout.startswith("alignment ")   # output as it was
    assert {f.name for f in page_figures(tmp_path / "one.html")} == ALL_FIGURES

    both = subprocess.run(eval_cmd + [str(a), str(b), "--html", str(tmp_path / "cmp.html"), "--json"],
                          capture_output=True, text=True, timeout=120)
    assert both.returncode == 0, both.stderr
    results = json.loads(both.stdout)
    assert list(results) == [str(a), str(b)] and results[str(b)]["ate_rmse"] > 5 * results[str(a)]["ate_rmse"]
    page = tmp_path / "cmp.html"
    assert f"wrote {page}" in both.stderr
    assert {f.name for f in page_figures(page)} == ALL_FIGURES   # b has no VIO state: a's is drawn
    text = page.read_text()
    rows = re.findall(r"<tr><td>([^<]*)</td>", text)
    assert rows == [str(a), str(b)]
    for path in (a, b):
        assert f"<td>{results[str(path)]['ate_rmse']:.4g}</td>" in text
    assert "one colour per run" in text and f"{b}: 1 loop closures accepted" in text
    for figure in page_figures(page):
        assert_drawn_png(figure)

    tables = subprocess.run(eval_cmd + [str(a), str(b)], capture_output=True, text=True, timeout=120)
    assert tables.stdout.startswith(f"== {a}\n{single.stdout}\n== {b}\nalignment "), tables.stdout


def chromium() -> str:
    path = shutil.which("chromium")
    assert path, "chromium not found: `make setup` (scripts/setup.sh) installs it from the OS packages"
    return path


def browser(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    """Headless Chromium (its own profile, no sandbox: the tests may run as root) with ``args``."""
    command = [chromium(), "--headless", "--disable-gpu", "--no-sandbox", "--hide-scrollbars",
               f"--user-data-dir={tmp_path / 'chromium-profile'}", *args]
    done = subprocess.run(command, capture_output=True, text=True, timeout=90)
    assert done.returncode == 0, done.stderr[-3000:]
    return done


IMAGE_CHECK = """<script>
window.addEventListener("load", () => {
  const out = document.createElement("pre");
  out.id = "image-check";
  out.textContent = JSON.stringify([...document.images].map(
    img => [img.getAttribute("src"), img.complete && img.naturalWidth > 0]));
  document.body.appendChild(out);
});
</script>
"""


def loaded_images(tmp_path: Path, page: Path) -> dict[str, bool]:
    """``{src: decoded}`` of every <img> on ``page`` after Chromium loaded it: the page with a small script that
    writes each image's state into the DOM once loading ended, saved beside it (same relative paths)."""
    probe = page.with_name("image_check.html")
    probe.write_text(page.read_text().replace("</body>", IMAGE_CHECK + "</body>"))
    dom = browser(tmp_path, "--virtual-time-budget=10000", "--dump-dom", probe.as_uri()).stdout
    found = re.search(r'<pre id="image-check">(.*?)</pre>', dom, re.S)
    assert found, dom[-2000:]
    return dict(json.loads(html.unescape(found.group(1))))


def test_report_loads_in_headless_chromium(tmp_path, full_report):
    page, run = full_report, full_report.parent
    images = loaded_images(tmp_path, page)
    assert images == {f"report_figures/{name}": True for name in ALL_FIGURES}

    shot = tmp_path / "shot.png"
    browser(tmp_path, f"--screenshot={shot}", "--window-size=1000,2600", page.as_uri())
    image = cv2.imread(str(shot), cv2.IMREAD_COLOR)
    assert image is not None and image.shape[:2] == (2600, 1000)
    non_white = (image < 240).any(axis=2).mean()
    assert image.std() > 20 and non_white > 0.05, (image.std(), non_white)

    # the check sees a broken image: a figure file gone
    (run / "report_figures" / "ate.png").unlink()
    images = loaded_images(tmp_path, page)
    assert not images["report_figures/ate.png"] and sum(images.values()) == len(ALL_FIGURES) - 1


def test_a_plotting_failure_in_vigs_run_is_a_warning(tmp_path, monkeypatch, capsys):
    """``vigs run`` plots last: when that fails, a warning says why and the outputs written before stand."""
    from types import SimpleNamespace

    import vigs_core.eval.report_html as report_html
    from vigs_core.system.pipeline import _write_html_report

    def broken(*args, **kwargs):
        raise RuntimeError("no fonts")

    run = write_run(tmp_path / "run", groundtruth())
    monkeypatch.setattr(report_html, "write_run_report", broken)
    _write_html_report(run, SimpleNamespace(groundtruth=None, T_BS=np.eye(4)), np.zeros(0, np.int64), True)
    assert "vigs run: report.html not written: RuntimeError: no fonts" in capsys.readouterr().err
    assert not (run / "report.html").exists() and (run / "report.json").is_file()


def test_a_graph_run_is_plotted_from_the_frontend_nodes_report(tmp_path):
    """The frontend node writes frontend_report.json (with the same frames, timings_s and vio as report.json): a
    graph run's folder gets every figure too."""
    gt = groundtruth()
    run = write_run(tmp_path / "graph", gt, loops=[[2, 17]])
    (run / "report.json").rename(run / "frontend_report.json")
    page = write_run_report(run, gt)
    assert {f.name for f in page_figures(page)} == ALL_FIGURES and not omitted(page)
