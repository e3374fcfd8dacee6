"""`benches/placements.py` and the `--copies` of `benches/step_costs.py`: each build is timed from
fresh copies of its files (new inodes, the same bytes), and the tables carry the copies' spread.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import poisson_rs as pr

ROOT = Path(__file__).resolve().parents[1]
# The benches are scripts, not part of the package: make their directory importable.
sys.path.insert(0, str(ROOT / "benches"))
import placements  # noqa: E402


def _package(tmp_path: Path) -> Path:
    pkg = tmp_path / "src" / "pkg"
    (pkg / "__pycache__").mkdir(parents=True)
    (pkg / "__pycache__" / "mod.cpython-311.pyc").write_bytes(b"stale")
    (pkg / "sub").mkdir()
    (pkg / "__init__.py").write_text("x = 1\n")
    (pkg / "sub" / "data.bin").write_bytes(bytes(range(256)) * 40)
    lib = pkg / "_core.so"
    lib.write_bytes(b"\x7fELF" + bytes(1000))
    lib.chmod(0o755)
    return pkg


def test_copies_are_new_files_with_the_same_bytes(tmp_path: Path) -> None:
    pkg = _package(tmp_path)
    copies = placements.fresh_copies(pkg, 3, tmp_path / "out")
    assert [c.name for c in copies] == ["pkg"] * 3
    assert len({c.parent for c in copies}) == 3
    inodes = {os.stat(pkg / "_core.so").st_ino}
    for c in copies:
        for rel in ("__init__.py", "sub/data.bin", "_core.so"):
            assert (c / rel).read_bytes() == (pkg / rel).read_bytes()
        inodes.add(os.stat(c / "_core.so").st_ino)
        assert os.access(c / "_core.so", os.X_OK)  # the mode is kept
        assert not (c / "__pycache__").exists()
    assert len(inodes) == 4  # no hard links: every copy is its own file


def test_a_single_file_is_copied_as_a_file(tmp_path: Path) -> None:
    lib = _package(tmp_path) / "_core.so"
    (copy,) = placements.fresh_copies(lib, 1, tmp_path / "out")
    assert copy.is_file() and copy.name == "_core.so"
    assert copy.read_bytes() == lib.read_bytes()
    assert os.stat(copy).st_ino != os.stat(lib).st_ino


@pytest.mark.parametrize("n", [0, -2])
def test_too_few_copies_are_refused_before_writing(tmp_path: Path, n: int) -> None:
    with pytest.raises(ValueError, match="at least 1"):
        placements.fresh_copies(_package(tmp_path), n, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_a_missing_source_is_refused_before_writing(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="does not exist"):
        placements.fresh_copies(tmp_path / "nothing", 2, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_ratio_range_pairs_every_copy_with_every_other() -> None:
    # now medians 3, before 1.5: ratio 2; extremes 2/2 and 4/1.
    assert placements.ratio_range([2.0, 3.0, 4.0], [1.0, 2.0]) == (2.0, 1.0, 4.0)
    assert placements.summary([5.0]) == (5.0, 5.0, 5.0)
    with pytest.raises(ValueError, match="no values"):
        placements.summary([])


def _step_costs(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "RAYON_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, str(ROOT / "benches" / "step_costs.py"), *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


def test_step_costs_times_each_build_from_its_copies(tmp_path: Path) -> None:
    # The baseline: this very package from another directory (same code, other files).
    base = tmp_path / "base"
    placements.fresh_copies(Path(pr.__file__).resolve().parent, 1, base)
    out = tmp_path / "costs.json"
    run = _step_costs(
        *("--system", "rigid-body", "--stepper", "midpoint", "--batch", "16"),
        *("--rounds", "2", "--copies", "2", "--baseline", str(base / "copy0")),
        *("--json", str(out)),
        cwd=tmp_path,
    )
    assert run.returncode == 0, run.stderr
    assert "now:" in run.stdout and "before:" in run.stdout and "2 fresh copies" in run.stdout
    data = json.loads(out.read_text())
    assert data["copies"] == 2
    assert [r["stepper"] for r in data["rows"]] == ["rk4", "midpoint"]
    for row in data["rows"]:
        for tag in ("", "_baseline"):
            per = row["ns_per_step_copies" + tag]
            assert len(per) == 2 and all(v > 0 for v in per)
            assert min(per) <= row["ns_per_step" + tag] <= max(per)
        lo, hi = row["vs_baseline_range"]
        assert lo <= row["vs_baseline"] <= hi
    # The same code: the same Newton updates from both builds (2 a step for the midpoint rule).
    mid = data["rows"][1]
    assert mid["newton_updates_per_step"] == mid["newton_updates_per_step_baseline"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--copies", "0"), "--copies must be at least 1"),
        (("--baseline", "nowhere"), "holds no poisson_rs package"),
    ],
)
def test_step_costs_refuses_bad_options_before_any_work(
    tmp_path: Path, args: tuple[str, ...], message: str
) -> None:
    out = tmp_path / "costs.json"
    run = _step_costs(*args, "--json", str(out), cwd=tmp_path)
    assert run.returncode != 0
    assert message in run.stderr
    assert "fresh copies" not in run.stdout  # no worker was started
    assert not out.exists()
