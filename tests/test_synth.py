"""The labelled scene generator (kbs.synth): geometry of the labels, occlusion, sensor laws,
determinism, the PLY export and the ``kbs synth`` command."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from plyfile import PlyData
from shapely.geometry import Point, Polygon

from kbs.errors import ParameterError
from kbs.io import read_cloud
from kbs.synth import HeightField, outdoor_scene, polyhedral_scene
from kbs.synth.polyhedral import box, wedge
from kbs.synth.raycast import pinhole_rays, ray_convex, ray_heightfield

POLY = dict(resolution=(120, 160))
OUTDOOR = dict(resolution=(180, 320))
NOISE = 0.002


@pytest.fixture(scope="module")
def poly():
    return polyhedral_scene(0, noise=NOISE, **POLY)


@pytest.fixture(scope="module")
def poly_clean():
    return polyhedral_scene(0, noise=0.0, **POLY)


@pytest.fixture(scope="module")
def outdoor():
    return outdoor_scene(0, **OUTDOOR)


@pytest.fixture(scope="module")
def outdoor_clean():
    return outdoor_scene(0, noise=0.0, **OUTDOOR)


def _same(a, b) -> bool:
    return (a.xyz.shape == b.xyz.shape and np.array_equal(a.xyz, b.xyz) and np.array_equal(a.labels, b.labels)
            and np.array_equal(a.objects, b.objects) and np.array_equal(a.pixel, b.pixel))


# --- kernels against brute force ------------------------------------------------------------------

def test_ray_convex_matches_brute_force_marching():
    rng = np.random.default_rng(7)
    solids = [box((1.0, 0.2), (0.4, 0.3, 0.5), 0.3, -1.0), wedge((1.2, -0.3), (0.5, 0.4, 0.3), 1.1, -1.0, 0.4),
              wedge((0.8, 0.0), (0.3, 0.5, 0.4), 2.0, -1.0, 0.0)]
    dirs = pinhole_rays((40, 40), (60.0, 60.0), 40.0)
    t_grid = np.linspace(0.0, 3.0, 6001)  # 0.5 mm steps
    for solid in solids:
        t, face = ray_convex(dirs, solid.normals, solid.offsets)
        sub = rng.choice(len(dirs), 300, replace=False)
        for i in sub:
            inside = solid.contains(t_grid[:, None] * dirs[i])
            if inside.any():
                assert t[i] == pytest.approx(t_grid[inside.argmax()], abs=1e-3)
                p = t[i] * dirs[i]
                assert abs(p @ solid.normals[face[i]] - solid.offsets[face[i]]) < 1e-9
            elif np.isfinite(t[i]):  # a graze thinner than the grid: on the solid, leaving it at once
                p = t[i] * dirs[i]
                assert solid.contains(p[None], margin=-1e-9)[0] and not solid.contains((p + 1e-3 * dirs[i])[None])[0]
        assert np.isfinite(t).any() and (~np.isfinite(t)).any()


def test_ray_heightfield_matches_fine_marching():
    rng = np.random.default_rng(3)
    field = HeightField(-1.5, np.array([0.1, 0.06, 0.04]), rng.uniform(-1.0, 1.0, (3, 2)), rng.uniform(0, 6, 3))
    dirs = pinhole_rays((30, 60), (40.0, 90.0), 15.0, rng=rng)
    t = ray_heightfield(dirs, field, 30.0)
    tt = np.arange(0.0, 30.0, 0.002)
    for i in rng.choice(len(dirs), 200, replace=False):
        P = tt[:, None] * dirs[i]
        under = P[:, 2] <= field(P[:, 0], P[:, 1])
        if under.any():
            assert t[i] == pytest.approx(tt[under.argmax()], abs=0.003)
        else:
            assert not np.isfinite(t[i])
    assert np.isfinite(t).mean() > 0.5


# --- determinism ----------------------------------------------------------------------------------

def test_same_seed_same_scene_other_seed_other_scene(poly, outdoor):
    assert _same(poly, polyhedral_scene(0, noise=NOISE, **POLY))
    assert not _same(poly, polyhedral_scene(1, noise=NOISE, **POLY))
    assert _same(outdoor, outdoor_scene(0, **OUTDOOR))
    assert not _same(outdoor, outdoor_scene(1, **OUTDOOR))


def test_no_global_random_state(poly):
    np.random.seed(123)
    before = np.random.get_state()[1].copy()
    polyhedral_scene(2, **POLY)
    assert np.array_equal(np.random.get_state()[1], before)


def test_invalid_parameters_raise_parameter_errors():
    with pytest.raises(ParameterError, match="'n_boxes' parameter of polyhedral_scene"):
        polyhedral_scene(n_boxes=-1)
    with pytest.raises(ParameterError, match="'resolution'"):
        polyhedral_scene(resolution=(0, 10))
    with pytest.raises(ParameterError, match="could not place"):
        polyhedral_scene(n_boxes=30, max_tries=20, **POLY)
    with pytest.raises(ParameterError, match="'ground_amplitude'"):
        outdoor_scene(ground_amplitude=2.0, sensor_height=1.5)


# --- polyhedral scenes ----------------------------------------------------------------------------

def test_polyhedral_points_lie_on_their_face_plane(poly, poly_clean):
    assert set(poly.faces) == set(np.unique(poly.labels).tolist()) == set(poly.normals_by_label)
    for label, face in poly.faces.items():
        on = poly.labels == label
        assert np.abs(face.distance(poly.xyz[on])).max() <= 5 * NOISE, face.name
        assert np.abs(face.distance(poly_clean.xyz[poly_clean.labels == label])).max() <= 1e-9
        assert np.linalg.norm(poly.normals_by_label[label]) == pytest.approx(1.0)
    # the noise is along the ray, with the asked standard deviation
    dr = np.linalg.norm(poly.xyz, axis=1) - np.linalg.norm(poly_clean.xyz, axis=1)
    assert np.array_equal(poly.pixel, poly_clean.pixel)
    assert abs(dr.mean()) < 1e-4 and dr.std() == pytest.approx(NOISE, rel=0.05)


def test_polyhedral_points_lie_inside_their_face_polygon(poly_clean):
    for label, face in poly_clean.faces.items():
        if face.polygon is None:  # the ground is unbounded
            continue
        n = face.normal
        a = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        polygon = Polygon(np.column_stack([face.polygon @ a, face.polygon @ b])).buffer(1e-7)
        P = poly_clean.xyz[poly_clean.labels == label]
        assert all(polygon.contains(Point(p @ a, p @ b)) for p in P), face.name


def test_polyhedral_occlusion_independent_check(poly_clean):
    """No point is hidden: the segment from the sensor to it stays outside every solid, and no
    point is inside a solid (point-membership tests, independent of the ray-plane algebra)."""
    X = poly_clean.xyz
    assert len(X) == poly_clean.shape[0] * poly_clean.shape[1]  # every ray meets the ground
    fractions = np.linspace(0.0, 1.0, 200)[1:-1]
    for solid in poly_clean.solids:
        assert not solid.contains(X, margin=1e-7).any()
        for f in fractions:
            assert not solid.contains(X * (f * (1 - 1e-6)), margin=1e-7).any()


def test_faces_turned_away_from_the_sensor_have_no_points():
    for seed in range(4):
        scene = polyhedral_scene(seed, **POLY)
        seen = {(f.object, f.name) for f in scene.faces.values()}
        for obj, solid in enumerate(scene.solids, start=1):
            back = {(obj, name) for name, d in zip(solid.face_names, solid.offsets) if d >= 0}
            assert (obj, "bottom") in back
            assert not (seen & back)
        for f in scene.faces.values():  # every face seen is seen from its outer side
            assert f.offset < 0


def test_polyhedral_labels():
    for seed in range(5):
        scene = polyhedral_scene(seed, **POLY)
        labels = np.unique(scene.labels)
        assert np.array_equal(labels, np.arange(len(labels)))  # contiguous face ids, 0 the ground
        assert np.array_equal(scene.ground, scene.labels == 0)
        assert np.array_equal(scene.ground, scene.objects == 0)
        assert 0.3 < scene.ground.mean() < 0.95
        n_boxes = scene.params["n_boxes"]
        for obj in range(1, len(scene.solids) + 1):
            faces = np.unique(scene.labels[scene.objects == obj])
            assert 1 <= len(faces) <= 3 or obj > n_boxes
            assert 0 not in faces
            assert all(scene.faces[f].object == obj for f in faces)
        assert scene.object_names[:2] == ("ground", "box 1") and scene.object_names[-1] == "wedge 1"


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), noise=st.sampled_from([0.0, 0.001, 0.005]))
def test_polyhedral_invariants_over_seeds(seed, noise):
    scene = polyhedral_scene(seed, noise=noise, resolution=(48, 64))
    labels = np.unique(scene.labels)
    assert np.array_equal(labels, np.arange(len(labels)))
    for label in labels:
        face = scene.faces[label]
        assert face.offset < 0  # seen from its outer side
        assert np.abs(face.distance(scene.xyz[scene.labels == label])).max() <= 6 * noise + 1e-9
    for obj in range(1, scene.params["n_boxes"] + 1):
        assert len(np.unique(scene.labels[scene.objects == obj])) <= 3


def test_polyhedral_solids_hide_each_other(poly_clean):
    """In this scene a solid stands in front of another: rays that would meet the far one alone
    show the near one, nearer; the far one keeps the rest of its pixels."""
    s = poly_clean
    dirs = pinhole_rays(s.shape, s.params["fov_deg"], s.params["tilt_deg"])[s.pixel]
    r = np.linalg.norm(s.xyz, axis=1)
    hidden_somewhere = 0
    for obj, solid in enumerate(s.solids, start=1):
        t, _ = ray_convex(dirs, solid.normals, solid.offsets)
        meets = np.isfinite(t)
        others = meets & (s.objects != obj)
        assert (s.objects[others] != 0).all() and (r[others] < t[others]).all()
        assert np.array_equal(s.objects[meets & ~others], np.full(np.count_nonzero(meets & ~others), obj))
        hidden_somewhere += np.count_nonzero(others)
    assert hidden_somewhere > 50


# --- outdoor scenes -------------------------------------------------------------------------------

def test_outdoor_labels_and_ground_mask(outdoor):
    assert np.array_equal(outdoor.ground, outdoor.labels == 0)
    assert np.array_equal(outdoor.labels, outdoor.objects)
    assert set(np.unique(outdoor.labels).tolist()) == {0, 1, 2, 3, 4}
    assert outdoor.object_names == ("ground", "rock 1", "rock 2", "rock 3", "bin")
    assert 0.5 < outdoor.ground.mean() < 0.99
    no_bin = outdoor_scene(0, with_bin=False, n_rocks=2, **OUTDOOR)
    assert set(np.unique(no_bin.labels).tolist()) == {0, 1, 2}


def test_outdoor_density_falls_with_range(outdoor):
    G = outdoor.xyz[outdoor.ground]
    r, az = np.hypot(G[:, 0], G[:, 1]), np.degrees(np.arctan2(G[:, 1], G[:, 0]))
    half = 30.0  # inside the 90 deg field of view

    def density(r1, r2):
        n = np.count_nonzero((r >= r1) & (r < r2) & (np.abs(az) <= half))
        return n / (np.radians(2 * half) / 2 * (r2**2 - r1**2))

    near, mid, far = density(3, 6), density(8, 12), density(15, 22)
    assert near > 4 * mid > 0 and mid > 4 * far > 0


def test_outdoor_keep_probability_follows_r0_over_r_squared():
    everything = outdoor_scene(0, density_r0=1e6, noise=0.0, **OUTDOOR)
    kept = outdoor_scene(0, density_r0=6.0, noise=0.0, **OUTDOOR)
    assert set(kept.pixel.tolist()) <= set(everything.pixel.tolist())  # same rays, a subset kept
    r_all = np.linalg.norm(everything.xyz, axis=1)
    r_kept = np.linalg.norm(kept.xyz, axis=1)
    band = (r_all > 10) & (r_all < 20)
    expected = ((6.0 / r_all[band]) ** 2).sum()
    observed = np.count_nonzero((r_kept > 10) & (r_kept < 20))
    assert abs(observed - expected) < 4 * np.sqrt(expected)
    assert np.count_nonzero(r_kept < 6) == np.count_nonzero(r_all < 6)


def test_outdoor_noise_grows_with_range_squared(outdoor, outdoor_clean):
    assert np.array_equal(outdoor.pixel, outdoor_clean.pixel)
    r_true = np.linalg.norm(outdoor_clean.xyz, axis=1)
    z = (np.linalg.norm(outdoor.xyz, axis=1) - r_true) / (outdoor.params["noise"] * r_true**2)
    assert abs(z.mean()) < 0.05 and z.std() == pytest.approx(1.0, rel=0.05)


def test_outdoor_points_on_their_surfaces_and_rocks_above_ground(outdoor_clean):
    s = outdoor_clean
    X, terrain = s.xyz, s.terrain
    g = s.ground
    assert np.abs(X[g, 2] - terrain(X[g, 0], X[g, 1])).max() < 1e-5
    n_rocks = s.params["n_rocks"]
    for i, rock in enumerate(s.solids[:n_rocks], start=1):
        P = X[s.labels == i]
        assert len(P) > 20
        assert (P[:, 2] >= terrain(P[:, 0], P[:, 1]) - 1e-6).all()  # what is seen is above ground
        assert rock.inside(P, tol=1e-6).all() and not rock.inside(P, tol=-1e-6).any()  # on the surface
        # partly buried: the rock's lowest lobe point is below the ground
        depth = np.sqrt(((rock.axes[:, :, 2] * rock.radii) ** 2).sum(axis=1))  # lowest point of each lobe
        lowest = rock.centers - depth[:, None] * [0.0, 0.0, 1.0]
        assert (lowest[:, 2] < terrain(lowest[:, 0], lowest[:, 1])).any()
    bin_ = s.solids[n_rocks]
    B = X[s.labels == n_rocks + 1]
    assert len(B) > 20 and (B[:, 2] <= bin_.top + 1e-9).all() and (B[:, 2] >= bin_.base - 1e-9).all()
    # sensor at the origin, the ground about sensor_height below
    assert np.median(X[g, 2]) == pytest.approx(-s.params["sensor_height"], abs=0.2)
    assert np.linalg.norm(X, axis=1).max() <= s.params["extent"]


# --- files and command line -----------------------------------------------------------------------

def test_save_writes_a_ply_that_reads_back(tmp_path, poly):
    path = tmp_path / "scene.ply"
    poly.save(path)
    cloud = read_cloud(path)
    assert np.array_equal(cloud.xyz, poly.xyz)
    assert np.array_equal(cloud.fields["label"], poly.labels)
    assert np.array_equal(cloud.fields["object"], poly.objects)
    assert np.array_equal(cloud.fields["ground"].astype(bool), poly.ground)
    assert np.array_equal(cloud.fields["pixel"], poly.pixel)
    comments = PlyData.read(str(path)).comments
    assert comments[0] == f"kbs synth: {poly.description}"
    faces = [c for c in comments if c.startswith("face ")]
    assert len(faces) == len(poly.faces)
    label, nx, ny, nz = (float(faces[-1].split()[i]) for i in (1, 5, 6, 7))
    assert np.allclose([nx, ny, nz], poly.normals_by_label[int(label)], atol=1e-8)


def kbs(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    exe = shutil.which("kbs", path=str(Path(sys.executable).parent)) or shutil.which("kbs")
    assert exe, "the kbs command is not installed"
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}
    return subprocess.run([exe, *args], capture_output=True, text=True, cwd=cwd, env=env, timeout=120)


@pytest.mark.slow
def test_kbs_synth_command_end_to_end(tmp_path):
    out = tmp_path / "poly.ply"
    r = kbs("synth", "polyhedral", "--seed", "3", "--resolution", "60x80", "--out", str(out))
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) == 1 and "4,800 points" in lines[0] and "faces" in lines[0] and "ground" in lines[0]
    expected = polyhedral_scene(3, resolution=(60, 80))
    cloud = read_cloud(out)
    assert np.array_equal(cloud.xyz, expected.xyz) and np.array_equal(cloud.fields["label"], expected.labels)

    out = tmp_path / "outdoor.ply"
    r = kbs("synth", "outdoor", "--seed", "1", "--rocks", "2", "--no-bin", "--resolution", "90x160", "--out", str(out))
    assert r.returncode == 0, r.stderr
    expected = outdoor_scene(1, n_rocks=2, with_bin=False, resolution=(90, 160))
    assert f"{len(expected):,} points" in r.stdout and "3 objects" in r.stdout
    assert np.array_equal(read_cloud(out).fields["label"], expected.labels)


def test_kbs_synth_errors_are_one_line_with_exit_codes(tmp_path, capsys):
    r = kbs("synth", "polyhedral", "--boxes", "60", "--resolution", "30x40")
    assert r.returncode == 6 and r.stderr.startswith("kbs: error: ") and len(r.stderr.splitlines()) == 1
    assert "could not place" in r.stderr
    from kbs.cli.main import main  # the same entry point, in-process (each subprocess costs ~1 s)

    assert main(["synth", "outdoor", "--resolution", "ten"]) == 2
    assert "ROWSxCOLS" in capsys.readouterr().err
    assert main(["synth", "polyhedral", "--resolution", "30x40", "--out", str(tmp_path / "missing" / "x.ply")]) == 3
    err = capsys.readouterr().err
    assert err.startswith("kbs: error: ") and "cannot write" in err and len(err.splitlines()) == 1


def test_kbs_synth_replaces_its_own_files_but_not_another_without_force(tmp_path, capsys):
    """Every synth command replaced any file at --out; now a file kbs did not write needs --force
    (checked before the scene is made), its own (a run id in the PLY; a drive's poses.txt by its
    digest in truth.json) is replaced; the SegComp rasters, with no room for a run id, need --force."""
    from kbs.cli.main import main
    from kbs.io.result import is_kbs_output

    def refused(args, path, text="mine"):
        assert main(args) == 3, args
        err = capsys.readouterr().err
        assert err.startswith(f"kbs: error: {path}: exists") and "--force" in err and len(err.splitlines()) == 1
        assert path.read_text() == text

    scene = tmp_path / "scene.ply"
    scene.write_text("mine")
    args = ["synth", "polyhedral", "--resolution", "20x30", "--out", str(scene)]
    refused(args, scene)
    assert main([*args, "--force"]) == 0 and is_kbs_output(scene)
    assert main(args) == 0  # its own
    drive = tmp_path / "drive"
    drive.mkdir()
    (drive / "poses.txt").write_text("mine")
    args = ["synth", "outdoor", "--frames", "2", "--resolution", "20x30", "--rocks", "1", "--out", str(drive)]
    refused(args, drive / "poses.txt")
    assert not (drive / "scans").exists()
    assert main([*args, "--force"]) == 0
    assert main(args) == 0  # its own: the frames by their run id, poses.txt by its digest
    (drive / "poses.txt").write_text((drive / "poses.txt").read_text() + "\n")  # changed since
    refused(args, drive / "poses.txt", (drive / "poses.txt").read_text())
    prefix = tmp_path / "abw"
    (tmp_path / "abw.gt-seg").write_text("mine")
    args = ["synth", "abw", "--boxes", "1", "--wedges", "0", "--out", str(prefix)]
    refused(args, tmp_path / "abw.gt-seg")
    assert not (tmp_path / "abw.range").exists()
    assert main([*args, "--force"]) == 0 and (tmp_path / "abw.range").exists()


def test_a_shorter_drive_over_a_longer_one_leaves_none_of_its_frames(tmp_path, capsys):
    """A drive of 2 frames written over one of 4: frames 000002-000003 stayed in scans/ beside the
    new poses.txt, and `kbs map DIR/scans` would have read 4 frames. kbs's own are removed; one kbs
    did not write is refused (exit 3, before the work) and removed only with --force."""
    from kbs.cli.main import main

    drive = tmp_path / "drive"
    args = ["synth", "outdoor", "--resolution", "20x30", "--rocks", "1", "--out", str(drive)]
    assert main([*args, "--frames", "4"]) == 0
    assert main([*args, "--frames", "2"]) == 0
    assert sorted(p.name for p in (drive / "scans").iterdir()) == ["000000.ply", "000001.ply"]
    (drive / "scans" / "000005.ply").write_text("mine")
    (drive / "scans" / "notes.ply").write_text("not a frame's name")
    capsys.readouterr()
    assert main([*args, "--frames", "1"]) == 3
    assert capsys.readouterr().err.startswith(f"kbs: error: {drive / 'scans' / '000005.ply'}: exists")
    assert (drive / "scans" / "000001.ply").exists()  # nothing done
    assert main([*args, "--frames", "1", "--force"]) == 0
    assert sorted(p.name for p in (drive / "scans").iterdir()) == ["000000.ply", "notes.ply"]
