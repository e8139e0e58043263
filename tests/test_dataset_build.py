"""`ttmjx demos` writes a dataset whole or not at all (training/dataset_build.py): a collection
cut short removes what it wrote into a new directory, keeps what --rebuild built there, and never
touches a directory that held something before."""
import os

import pytest

from training import dataset_build
from ttmjx.world.config import World


def cut_short(cfg, source, n, seed, out, backend, **kw):
    """make_dataset stopped by Ctrl-C after it wrote part of the dataset."""
    os.makedirs(out, exist_ok=True)
    open(os.path.join(out, "trajectories.npz.tmp"), "w").close()
    raise KeyboardInterrupt


def test_a_dataset_cut_short_leaves_no_partial_files(monkeypatch, tmp_path):
    monkeypatch.setattr(dataset_build.demos, "make_dataset", cut_short)
    out = str(tmp_path / "new")
    with pytest.raises(KeyboardInterrupt):
        dataset_build.dataset(World(), "striker", 4, 0, out)
    assert not os.path.exists(out)
    # an --out that already held something (a rebuild's bootstrap/) keeps all of it
    held = tmp_path / "held"
    (held / "bootstrap").mkdir(parents=True)
    with pytest.raises(KeyboardInterrupt):
        dataset_build.dataset(World(), "striker", 4, 0, str(held))
    assert sorted(os.listdir(held)) == ["bootstrap", "trajectories.npz.tmp"]


def test_remove_partial_keeps_what_it_is_told(tmp_path):
    (tmp_path / "out" / "bootstrap").mkdir(parents=True)
    (tmp_path / "out" / "part").mkdir()
    (tmp_path / "out" / "file.npz").write_text("x")
    dataset_build.remove_partial(str(tmp_path / "out"), keep=("bootstrap",))
    assert os.listdir(tmp_path / "out") == ["bootstrap"]
    dataset_build.remove_partial(str(tmp_path / "out"))
    assert not (tmp_path / "out").exists()
