"""Every notebook in analysis/ runs on the data committed in the repository (papermill, its
`parameters` cell at the defaults) and draws its figures; one also runs on other data."""
import json
from pathlib import Path

import pytest

ANALYSIS = Path(__file__).resolve().parents[1] / "analysis"
NOTEBOOKS = sorted(ANALYSIS.glob("*.ipynb"))


def _execute(notebook: Path, out: Path, **parameters) -> dict:
    import papermill

    papermill.execute_notebook(str(notebook), str(out), parameters=parameters, cwd=str(ANALYSIS),
                               kernel_name="python3", progress_bar=False)
    return json.loads(out.read_text())


def _images(nb: dict) -> int:
    return sum("image/png" in o.get("data", {}) for c in nb["cells"] for o in c.get("outputs", []))


@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=[n.stem for n in NOTEBOOKS])
def test_notebook_runs_on_the_committed_data(notebook, tmp_path):
    nb = _execute(notebook, tmp_path / notebook.name)
    assert _images(nb) >= 1


def test_a_notebook_takes_its_data_dir_as_a_parameter(tmp_path):
    from test_aggregate import make_run

    for length, value in ((1, 2.0), (3, 7.0)):
        for seed in (0, 1):
            make_run(tmp_path / "runs", f"fl{length}_s{seed}", {"fragment_len": length, "seed": seed},
                     lambda t, v=value + seed: v)
    nb = _execute(ANALYSIS / "figA4_scaling.ipynb", tmp_path / "out.ipynb", a_dir=str(tmp_path / "runs"),
                  b_dir=str(tmp_path / "none"), c_dir=str(tmp_path / "none"))  # A.4A's table alone
    texts = ["".join(o["data"]["text/plain"]) for c in nb["cells"] for o in c.get("outputs", [])
             if "text/plain" in o.get("data", {})]
    tables = [t for t in texts if "iqm" in t]
    assert len(tables) == 1 and "7.5" in tables[0] and "2.5" in tables[0]   # IQM of 7, 8 and of 2, 3


def test_fragment_choices_draw_the_go_to_target_record_too(tmp_path):
    """Fig. A.5 / A.6 default to the vision agent's record; the go_to_target record draws with
    record_dir=, its Fig. A.6 episode chosen as a walk into the target zone (not a spawn in it)."""
    nb = _execute(ANALYSIS / "figA5_A6_fragment_choices.ipynb", tmp_path / "out.ipynb",
                  record_dir="docs/results/fig_a5_a6/record")
    assert _images(nb) == 2
    assert "218 episodes" in _text(nb)
    reward = _a6_episode(nb, "docs/results/fig_a5_a6/record")["reward"]
    assert reward[0] == 0 and reward.sum() > 0  # walked into the zone; a spawn in it is rewarded at once


def test_fragment_choices_draw_the_best_episode_of_a_vision_task(tmp_path):
    import numpy as np

    nb = _execute(ANALYSIS / "figA5_A6_fragment_choices.ipynb", tmp_path / "out.ipynb")
    record = ANALYSIS.parent / "docs/results/fig7_saliency/record"
    best = max(np.load(p)["reward"].sum() for p in (record / "episodes").glob("episode_*.npz"))
    assert _a6_episode(nb, record)["reward"].sum() == best


def _text(nb: dict) -> str:
    return "".join("".join(o.get("text", "")) for c in nb["cells"] for o in c.get("outputs", []))


def _a6_episode(nb: dict, record) -> dict:
    """The episode Fig. A.6 drew, read from the record by the index the notebook printed."""
    import numpy as np

    [line] = [t for t in _text(nb).splitlines() if t.startswith("Fig. A.6: episode")]
    index = int(line.split()[3].rstrip(","))
    paths = sorted((ANALYSIS.parent / record / "episodes").glob("episode_*.npz"))
    with np.load(paths[index]) as ep:
        return {k: ep[k] for k in ep.files}
