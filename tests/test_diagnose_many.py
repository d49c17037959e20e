"""DEV-03: diagnosis of renderers that differ in many ways at once (oracle/search.py,
oracle/stage_probes.py, oracle/residual.py, oracle/meta/many.py).

The default run diagnoses one image-only renderer with eight catalogue deviations and two
off-catalogue defects (its report page drawn), and checks the stage probes' ladder and the
localisation rule without rendering much.  The slow run is the table of
docs/spec/deviations.md: 20 seeded sets of each size 4, 6, 8, 10, 12 and every off-catalogue
defect alone and in pairs; at size 8 it requires recall >= 90 % and precision >= 95 %, and every
off-catalogue defect's stage named.
"""
from __future__ import annotations

import numpy as np
import pytest

import refgs
from oracle.diagnose import diagnose
from oracle.html import write_diagnosis_page
from oracle.meta.many import catalogue_sets, off_catalogue_sets, run_set, table
from oracle.meta.offcatalogue import DEFECTS, OffCatalogue
from oracle.residual import localise, parting_stages
from oracle.stage_probes import STAGE_PROBES, base_chain, stage_probe_cases

#: the acceptance bars at eight simultaneous catalogue deviations (issue 51)
RECALL_AT_8, PRECISION_AT_8 = 0.90, 0.95
#: where each off-catalogue defect first shows on the ladder (its base agrees)
FIRST_PARTING = {"cov_rotation_sign": {"rotated", "rotated_x"},
                 "ellipse_mirrored": {"rotated", "off_axis"},
                 "sh_x_sign": {"sh_view"}, "sort_by_distance": {"sort_key"}}


def _differing(backend) -> set:
    out = set()
    for p, c in stage_probe_cases():
        ref = refgs.render(c.gaussians, c.camera, c.config)
        got = backend.render(c.gaussians, c.camera, c.config)
        if not np.allclose(ref.image, got["image"], rtol=0, atol=1e-12):
            out.add(p.name)
    return out


def test_dev03_ladder_is_rooted_and_every_probe_says_what_it_isolates():
    for name, p in STAGE_PROBES.items():
        assert p.clauses and p.adds and p.claim, name
        assert base_chain(name)[-1:] in ([], ["centre"]), name
    assert STAGE_PROBES["centre"].base is None


@pytest.mark.parametrize("defect", sorted(DEFECTS))
def test_dev03_each_off_catalogue_defect_first_shows_where_designed(defect):
    """Without catalogue deviations each planted defect makes exactly the designed probes (and
    probes built on them) differ, and the ladder places it at its stage."""
    diff = _differing(OffCatalogue((), {defect}))
    first = {n for n in diff if STAGE_PROBES[n].base not in diff}
    assert first == FIRST_PARTING[defect], diff
    rows = [{"name": n, "status": "differ", "distance": 1.0} for n in STAGE_PROBES if n in diff]
    loc = localise(rows, [])
    assert loc["first"] == DEFECTS[defect][0] and loc["stages"] == [DEFECTS[defect][0]], loc


def test_dev03_two_defects_are_placed_at_two_stages():
    """A covariance defect and a sort-key defect: the fewest stages that explain the probes
    are COV and RAS, not the projection that both probes also pass through."""
    rows = [{"name": n, "status": "differ", "distance": 1.0} for n in ("rotated", "rotated_x", "sort_key")]
    assert set(parting_stages(rows).values()) == {"COV", "RAS"}
    rows = [{"name": n, "status": "differ", "distance": 1.0} for n in ("rotated", "off_axis")]
    assert set(parting_stages(rows).values()) == {"PRJ"}


def test_dev03_eight_deviations_and_two_defects_named_localised_and_drawn(tmp_path):
    """Eight catalogue deviations, a mirrored ellipse and a sort by distance, image only: the
    eight are named and nothing else, PRJ and RAS are where the outputs part, and
    diagnosis.html shows the stage probes first, then the named set, then what is left, with
    pictures.  (A covariance deviation beside the mirrored ellipse can be taken for another:
    quaternions read x, y, z, w with the conic mirrored look much like a transposed rotation;
    the slow table counts such cases.)"""
    devs = frozenset({"near_cull_off", "no_dilation", "colour_clamp_01", "alpha_skip_off",
                      "sh_dir_reversed", "pixel_centre_0", "no_background", "stop_off"})
    defects = frozenset({"ellipse_mirrored", "sort_by_distance"})
    r = diagnose(OffCatalogue(devs, defects), checks=[], verify_set=False, pictures=tmp_path / "pictures")
    assert set(r["deviations"]) == devs, r["search"]["trace"]
    assert r["residual"]["stages"] == ["PRJ", "RAS"], r["residual"]
    assert "outputs first part at the projection (PRJ)" in r["summary"]
    page = write_diagnosis_page(r, tmp_path).read_text()
    order = [page.index(h) for h in ("<h3>Stage probes", "<h3>The named set", "<h3>What is left")]
    assert order == sorted(order)
    left = page[order[2]:]
    assert "projection (PRJ): " in left and "in a way the catalogue does not name" in left
    assert 'src="pictures/stage-centre.png"' in page and 'src="pictures/stage-sort_key-residual.png"' in page
    assert (tmp_path / "pictures" / "stage-off_axis-residual.png").stat().st_size > 0


@pytest.mark.slow
def test_dev03_recall_and_precision_at_scale():
    """The table of docs/spec/deviations.md (python -m oracle.meta.many, seed 0)."""
    rows = [run_set(s) for size in (4, 6, 8, 10, 12) for s in catalogue_sets(size, 20, seed=0)]
    rows += [run_set(d, f) for d, f in off_catalogue_sets(seed=0)]
    print(table(rows))
    at8 = [r for r in rows if len(r["planted"]) == 8 and not r["defects"]]
    tp, planted, named = (sum(r[k] for r in at8) for k in ("tp", "n_planted", "n_named"))
    assert tp / planted >= RECALL_AT_8 and tp / named >= PRECISION_AT_8, table(rows)
    missed = [(r["defects"], r["residual"]) for r in rows if not all(r["defect_stages_named"].values())]
    assert not missed, missed
