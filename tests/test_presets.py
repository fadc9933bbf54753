"""Material presets: the published warp/weft values they carry (one table, cloth_warp.materials.WANG_2011),
the documents that cite them, and the textile tests of benchmarks/calibrated_presets.py on a coarse grid."""

import json
import math
import pathlib
import re
import sys

import pytest

from cloth_warp.materials import PRESETS, WANG_2011, WANG_2011_PRESETS, FabricMaterial

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
import calibrated_presets as cp  # noqa: E402


@pytest.mark.parametrize("name", sorted(WANG_2011_PRESETS))
def test_woven_presets_carry_wang_2011_values(name):
    """Check each measured preset is its fabric's row in the convention stated: warp = u, stretch 2c, G = c33,
    warp bending = the 90 deg row (hinges across the warp), weft bending = the 0 deg row."""
    m, d = PRESETS[name], WANG_2011[WANG_2011_PRESETS[name]]
    c11, _, c22, c33 = d["stretching"]
    b0, _, b90 = d["bending"]
    assert (m.areal_density, m.stretch_stiffness, m.stretch_weft, m.shear_stiffness) == (d["density"], 2 * c11, 2 * c22, c33)
    assert (m.bend_stiffness, m.bend_weft) == (b90, b0)
    assert m.stretch_stiffness_weft is not None and m.bend_stiffness_weft is not None  # anisotropic, not a fallback


def test_isotropic_presets_stay_isotropic():
    """Check the presets without warp/weft data (cotton, silk, wool) carry no weft values."""
    for name in set(PRESETS) - set(WANG_2011_PRESETS):
        assert PRESETS[name].stretch_stiffness_weft is None and PRESETS[name].bend_stiffness_weft is None, name


def test_measurement_table_matches_the_document():
    """Check WANG_2011 against docs/fabric-measurements.md table 1.2 (raw c11, c12, c22, c33 to 0.1 N/m, the
    0/45/90 deg bending to 0.1e-6 N m, rho_A): a typo in either fails."""
    text = (ROOT / "docs" / "fabric-measurements.md").read_text()
    seen = set()
    for fabric, d in WANG_2011.items():
        row = re.search(rf"^\| {re.escape(fabric)} \|(.*)$", text, re.M)
        assert row, fabric
        cells = [c.strip() for c in row.group(1).split("|")]
        assert float(cells[1]) == d["density"]
        assert [float(v) for v in cells[2].split(",")] == pytest.approx(d["stretching"], abs=0.051)
        assert [float(v) for v in cells[7].split("/")] == pytest.approx([b * 1e6 for b in d["bending"]], abs=0.051)
        seen.add(fabric)
    assert len(seen) == len(WANG_2011)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_have_a_positive_definite_membrane(name):
    """Check every preset's free-strip stiffness is positive in warp, weft and bias (C_w C_f > G^2: the
    spring lattice's coupling is G), and at most the value held laterally."""
    m = PRESETS[name]
    assert m.stretch_stiffness * m.stretch_weft > m.shear_stiffness**2
    for angle, held in ((0.0, m.stretch_stiffness), (90.0, m.stretch_weft)):
        assert 0.0 < m.stretch_stiffness_at(angle) <= held * (1 + 1e-9)
    assert m.stretch_stiffness_at(45.0) > 0.0


@pytest.mark.parametrize("chord,alpha", [(30.0, 4.921), (41.5, 8.004), (45.0, 9.254), (60.0, 18.22)])
def test_elastica_inversion_matches_physics_md(chord, alpha):
    """Check the chord angle <-> alpha of the benchmark's heavy elastica against docs/physics.md 1(a)."""
    assert cp.elastica_alpha(chord) == pytest.approx(alpha, rel=2e-3)


@pytest.mark.parametrize("direction", ["warp", "weft"])
def test_denim_cantilever_bending_length_warp_and_weft(device, direction):
    """Check ASTM D1388 on denim strips cut along the warp and the weft (16 x 3 cells, 25 mm wide): the simulated
    bending length is (B / (rho_A g))^(1/3) of that direction within 3 % (measured +0.6 % on the weft)."""
    r = cp.cantilever_bending_length(PRESETS["denim"], direction, device, segments=16, steps=80)
    m = PRESETS["denim"]
    b = m.bend_stiffness if direction == "warp" else m.bend_weft
    expected = (b / (m.areal_density * 9.81)) ** (1.0 / 3.0)
    assert r["simulated"] == pytest.approx(expected, rel=0.03)
    assert r["max_speed"] < 1e-3  # at rest


def test_polyester_free_strip_tensile_stiffness(device):
    """Check a hanging polyester strip along the warp stretches as the free strip C (1 - G^2 / (C_w C_f)) within
    1 % (measured +0.07 %): the preset's 86 N/m, not the old 1200 N/m."""
    r = cp.tensile_stiffness(PRESETS["polyester"], "warp", device)
    assert r["simulated"] == pytest.approx(r["free_strip"], rel=0.01)
    assert r["free_strip"] < r["published"]


def test_calibrated_table_is_current():
    """Check benchmarks/results/calibrated_presets.json covers every preset with the values they have now
    (re-run benchmarks/calibrated_presets.py after changing a preset)."""
    path = ROOT / "benchmarks" / "results" / "calibrated_presets.json"
    results = json.loads(path.read_text())["results"]
    assert set(results) == set(PRESETS)
    for name, r in results.items():
        m: FabricMaterial = PRESETS[name]
        assert r["cantilever"]["warp"]["published"] == pytest.approx(m.bending_length, rel=1e-9), name
        assert r["cantilever"]["weft"]["published"] == pytest.approx(m.bending_length_weft, rel=1e-9), name
        assert r["tensile"]["warp"]["published"] == pytest.approx(m.stretch_stiffness, rel=1e-9), name
        assert r["tensile"]["weft"]["published"] == pytest.approx(m.stretch_weft, rel=1e-9), name
        for d in ("warp", "weft"):
            assert math.isfinite(r["cantilever"][d]["simulated"]) and math.isfinite(r["tensile"][d]["simulated"])
