"""``wheelgrid plan`` end to end on map_server files: JSON, Table II text, PNG, exit codes."""

import json
import warnings

import numpy as np
import pytest

from wheelgrid_common.map_io import Grid, write_map
from wheelgrid_nav.cli_plan import main

PAPER_OCCUPIED = [(3, 0), (3, 1), (3, 2), (3, 3), (3, 4), (5, 0), (5, 1), (5, 2), (5, 3), (4, 4)]
PAPER_ROUTE = [[2, 0]] + [[2, c] for c in range(1, 6)] + [[r, 5] for r in range(3, 7)]


@pytest.fixture
def paper_yaml(tmp_path):
    g = np.zeros((8, 8), dtype=np.int8)
    for r, c in [*PAPER_OCCUPIED, (6, 7)]:
        g[r, c] = 100
    g[0, 7] = -1  # an unknown corner
    # 1.2 m cells (a wheelchair footprint), lower-left corner at (1, 2) in the map frame
    return write_map(tmp_path / "grid.yaml", Grid(g, 1.2, (1.0, 2.0, 0.0)))


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_json_route_and_table_ii_actions(paper_yaml, capsys):
    code, out, err = run(
        capsys, paper_yaml, "--start", "2,0", "--goal", "6,5", "--heading", "down", "--json"
    )
    assert code == 0, err
    doc = json.loads(out)
    assert doc["cells"] == PAPER_ROUTE
    assert doc["moves"] == ["right"] * 5 + ["down"] * 4
    assert doc["converged"] is True and doc["episodes"] > 0 and doc["seconds"] > 0
    acts = doc["actions"]
    assert [a["action"] for a in acts] == (
        ["left-forward"] + ["forward"] * 4 + ["right-forward"] + ["forward"] * 3
    )
    assert acts[0] == {
        "from": [2, 0],
        "to": [2, 1],
        "heading": "down",
        "move": "right",
        "new_heading": "right",
        "action": "left-forward",
    }


def test_json_without_heading_has_no_actions(paper_yaml, capsys):
    code, out, _ = run(capsys, paper_yaml, "--start", "2,0", "--goal", "6,5", "--json")
    assert code == 0
    doc = json.loads(out)
    assert doc["cells"] == PAPER_ROUTE and "actions" not in doc


def test_metres_in_the_map_frame(paper_yaml, capsys):
    # cell (2, 0) centre: x = 1 + 0.6, y = 2 + (8 - 2 - 0.5) * 1.2; (6, 5): x = 1 + 5.5 * 1.2
    code, out, err = run(
        capsys,
        paper_yaml,
        "--start-xy",
        f"{1.6},{2 + 5.5 * 1.2}",
        "--goal-xy",
        f"{1 + 5.5 * 1.2 + 0.3},{2 + 1.5 * 1.2 - 0.3}",
        "--json",
    )
    assert code == 0, err
    assert json.loads(out)["cells"] == PAPER_ROUTE


def test_a_refused_plan_leaves_no_picture_of_an_earlier_route(paper_yaml, tmp_path, capsys):
    """A start in an occupied cell was refused (exit 2), and the --png path still held the
    previous plan's picture with its route: another route under the name asked for (a
    review). A grid that does not read is refused the same way."""
    png = tmp_path / "plan.png"
    code, _, err = run(capsys, paper_yaml, "--start", "2,0", "--goal", "6,5", "--png", png)
    assert code == 0 and png.is_file(), err
    code, _, err = run(capsys, paper_yaml, "--start", "3,0", "--goal", "6,5", "--png", png)
    assert code == 2 and "not free" in err, err
    assert not png.exists()
    run(capsys, paper_yaml, "--start", "2,0", "--goal", "6,5", "--png", png)
    code, _, err = run(capsys, tmp_path / "none.yaml", "--start", "2,0", "--goal", "6,5",
                       "--png", png)  # fmt: skip
    assert code == 2 and "cannot read grid" in err and not png.exists(), err
    # a file that is no picture is neither replaced nor removed: `--png grid.yaml`
    before = paper_yaml.read_bytes()
    code, _, err = run(capsys, paper_yaml, "--start", "3,0", "--goal", "6,5", "--png", paper_yaml)
    assert code == 2 and "is not a PNG picture: not replaced" in err, err
    assert paper_yaml.read_bytes() == before
    # nor a picture this command did not write (`wheelgrid grid`'s Fig. 12), on a refusal or
    # a route (a route's picture replaced it: a review)
    from PIL import Image

    fig = tmp_path / "grid.png"
    Image.new("RGB", (50, 50), "red").save(fig)
    drawn = fig.read_bytes()
    for start in ("3,0", "2,0"):
        code, _, err = run(capsys, paper_yaml, "--start", start, "--goal", "6,5", "--png", fig)
        assert code == 2 and "did not write (grid.png" in err and fig.read_bytes() == drawn, err
    # nor the map's own PNG image, which would have been gone before the map was read
    image = tmp_path / "map.png"
    Image.fromarray(np.full((8, 8), 254, np.uint8)).save(image)
    (tmp_path / "map.yaml").write_text(
        "image: map.png\nresolution: 1.2\norigin: [0, 0, 0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    kept = image.read_bytes()
    code, _, err = run(capsys, tmp_path / "map.yaml", "--start", "2,0", "--goal", "6,5",
                       "--png", image)  # fmt: skip
    assert code == 2 and "did not write" in err and image.read_bytes() == kept, err


def test_heading_method_table_and_png(paper_yaml, tmp_path, capsys):
    from PIL import Image

    png = tmp_path / "plan.png"
    code, out, err = run(
        capsys,
        paper_yaml,
        "--start",
        "2,0",
        "--goal",
        "6,5",
        "--heading",
        "down",
        "--method",
        "qlearning-heading",
        "--seed",
        "5",
        "--png",
        png,
    )
    assert code == 0, err
    lines = out.splitlines()
    assert "Actual action" in lines[0]
    assert lines[2].split() == ["(2,0)", "to", "(2,1)", "Down", "Right", "Right", "Left-Forward"]
    assert lines[7].split()[-1] == "Right-Forward"
    with Image.open(png) as im:
        img = np.asarray(im.convert("RGB"))
    px = 48  # render_plan's cell size for a small grid
    # the grid, and below it the words for what it shows (there were none; a review)
    assert img.shape[1] >= 8 * px and img.shape[0] > 8 * px
    from wheelgrid_nav.plan_png import plan_caption

    words = plan_caption([(2, 0), (2, 1), (3, 1)], (2, 0), (3, 1), "ok")
    assert "green: start (2, 0)" in words and "blue arrows: the route, 2 moves" in words
    assert "no route: unreachable" in plan_caption([], (2, 0), (3, 1), "unreachable")
    caption_band = img[8 * px :, :]
    assert (caption_band.sum(axis=2) < 300).any()  # dark text on the white band

    def centre(r, c):
        return tuple(int(v) for v in img[r * px + 2, c * px + 2])

    assert centre(2, 0) == (40, 180, 60)  # start green
    assert centre(6, 5) == (220, 40, 40)  # goal red
    assert centre(3, 0) == (0, 0, 0)  # occupied black
    assert centre(0, 7) == (150, 150, 150)  # unknown grey
    # the blue arrow crosses the middle of a route cell
    mid = img[2 * px + px // 2, 3 * px : 4 * px]
    assert any(tuple(int(v) for v in p) == (30, 80, 230) for p in mid)


@pytest.mark.parametrize(
    ("start", "goal", "message"),
    [
        ("3,0", "6,5", "start cell (3,0) is not free"),
        ("2,0", "0,7", "goal cell (0,7) is not free"),
        ("2,0", "8,0", "outside"),
        ("-1,0", "6,5", "start cell (-1,0) is outside"),  # a negative value, not an option
        ("0,7", "0,7", "goal cell (0,7) is not free"),  # unknown start may not be the goal
    ],
)
def test_bad_cells_exit_2(paper_yaml, capsys, start, goal, message):
    code, _, err = run(capsys, paper_yaml, "--start", start, "--goal", goal)
    assert code == 2 and message in err and "Traceback" not in err


def test_unreachable_goal_exit_2(tmp_path, capsys):
    g = np.zeros((4, 6), dtype=np.int8)
    g[:, 3] = 100
    yaml_path = write_map(tmp_path / "split.yaml", Grid(g, 1.0))
    code, out, err = run(capsys, yaml_path, "--start", "0,0", "--goal", "0,5", "--json")
    assert code == 2 and "cannot be reached" in err
    assert json.loads(out)["cells"] == []


def test_not_converged_exit_1_and_no_route(paper_yaml, tmp_path, capsys):
    cfg = tmp_path / "planner.yaml"
    cfg.write_text("planner:\n  max_episodes: 1\n  check_every: 1\n")
    code, out, err = run(
        capsys, paper_yaml, "--start", "2,0", "--goal", "6,5", "--config", cfg, "--json"
    )
    assert code == 1 and "not converged" in err
    doc = json.loads(out)
    assert doc["converged"] is False and doc["cells"] == [] and doc["moves"] == []


def test_flag_errors_exit_2(paper_yaml, tmp_path, capsys):
    assert run(capsys, paper_yaml, "--goal", "6,5")[0] == 2
    assert run(capsys, paper_yaml, "--start", "2,0", "--start-xy", "1,1", "--goal", "6,5")[0] == 2
    assert run(capsys, paper_yaml, "--start", "2;0", "--goal", "6,5")[0] == 2
    code, _, err = run(capsys, tmp_path / "missing.yaml", "--start", "2,0", "--goal", "6,5")
    assert code == 2 and "cannot read grid" in err
    with pytest.raises(SystemExit) as exc:
        main([str(paper_yaml), "--start", "2,0", "--goal", "6,5", "--method", "dijkstra"])
    assert exc.value.code == 2
    code, _, err = run(
        capsys, paper_yaml, "--start", "2,0", "--goal", "6,5", "--method", "qlearning-heading"
    )
    assert code == 2 and "heading" in err


def test_negative_seed_exit_2(paper_yaml, tmp_path, capsys):
    code, _, err = run(capsys, paper_yaml, "--start", "2,0", "--goal", "6,5", "--seed", "-1")
    assert code == 2 and "seed must be a non-negative integer" in err and "Traceback" not in err
    cfg = tmp_path / "seed.yaml"
    cfg.write_text("seed: -5\n")
    code, _, err = run(capsys, paper_yaml, "--start", "2,0", "--goal", "6,5", "--config", cfg)
    assert code == 2 and "got -5" in err


def test_huge_check_every_is_refused_not_a_hang(paper_yaml, tmp_path, capsys):
    cfg = tmp_path / "ce.yaml"
    cfg.write_text("check_every: 1000000000\nmax_seconds: 1\n")
    code, _, err = run(capsys, paper_yaml, "--start", "2,0", "--goal", "6,5", "--config", cfg)
    assert code == 2 and "check_every must be from 1 to" in err


@pytest.mark.parametrize("setting", ["replay: 100000000", "agents: 1000000000"])
def test_a_replay_history_too_large_to_keep_is_exit_2(paper_yaml, tmp_path, capsys, setting):
    """replay 1e8 or agents 1e9 passed the settings check and ended in a 38.7 GiB allocation
    error, a 17-line traceback, exit 1 (a review's find)."""
    cfg = tmp_path / "big.yaml"
    cfg.write_text(f"{setting}\n")
    code, _, err = run(capsys, paper_yaml, "--start", "2,0", "--goal", "6,5", "--config", cfg)
    says = "GiB of history" if setting.startswith("replay") else "(memory): lower agents"
    assert code == 2 and says in err and "Traceback" not in err, err


@pytest.mark.parametrize("where", ["missing/plan.png", "."])
def test_unwritable_png_exit_2_before_planning(paper_yaml, tmp_path, capsys, where):
    png = tmp_path / where
    code, out, err = run(
        capsys, paper_yaml, "--start", "2,0", "--goal", "6,5", "--json", "--png", png
    )
    assert code == 2 and "cannot write --png" in err and "Traceback" not in err
    assert out == ""  # refused before training, so no result is printed


def test_negative_map_coordinates(tmp_path, capsys):
    """argparse reads "-0.5,1" as an option; the coordinate flags must take it as a value."""
    g = np.zeros((4, 4), dtype=np.int8)
    yaml_path = write_map(tmp_path / "neg.yaml", Grid(g, 1.0, (-3.0, -2.0, 0.0)))
    # (-2.5, 1.5) is column 0, row 4 - 1 - 3 = 0; (-0.5, -1.5) is column 2, row 3
    code, out, err = run(
        capsys, yaml_path, "--start-xy", "-2.5,1.5", "--goal-xy", "-0.5,-1.5", "--json"
    )
    assert code == 0, err
    doc = json.loads(out)
    assert doc["cells"][0] == [0, 0] and doc["cells"][-1] == [3, 2]
    # an abbreviated flag and a quoted value with a space work too
    code, out, err = run(capsys, yaml_path, "--start-x", "-2.5, 1.5", "--goal", "3,2", "--json")
    assert code == 0, err
    assert json.loads(out)["cells"][0] == [0, 0]
    # a negative point off the grid is an ordinary one-line refusal
    code, _, err = run(capsys, yaml_path, "--start-xy", "-9,1", "--goal", "3,2")
    assert code == 2 and "outside" in err


@pytest.mark.parametrize("xy", ["nan,1", "1,inf", "-inf,1", "-nan,0"])
def test_non_finite_coordinates_exit_2(paper_yaml, capsys, xy):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no numpy RuntimeWarning on the way
        code, _, err = run(capsys, paper_yaml, "--start-xy", xy, "--goal", "6,5")
    assert code == 2 and "is not finite" in err and "Traceback" not in err


def test_far_coordinates_exit_2_without_overflow(paper_yaml, capsys):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        code, _, err = run(capsys, paper_yaml, "--start", "2,0", "--goal-xy", "1e300,-1e300")
    assert code == 2 and "outside the 8x8 grid" in err


def test_cells_smaller_than_the_chair_are_refused(tmp_path, capsys):
    """The fine map (5 cm) and 0.6 m cells planned through a 70 cm gap, exit 0: one cell is
    the chair's place, and a cell smaller than the chair can be a gap it does not fit."""
    g = np.zeros((3, 8), np.int8)
    for res in (0.05, 0.6):
        yaml_path = write_map(tmp_path / f"g{res}.yaml", Grid(g, res))
        code, _, err = run(capsys, yaml_path, "--start", "1,0", "--goal", "1,7")
        assert code == 2 and "smaller than the chair (1 m)" in err, err
    code, _, err = run(
        capsys, write_map(tmp_path / "g1.yaml", Grid(g, 1.0)), "--start", "1,0", "--goal", "1,7"
    )
    assert code == 0, err
