"""`benches/build_core.sh`: a revision's extension built as the wheel is built, for the benches.

`cargo` is replaced by a stand-in on PATH that records its arguments and writes a library file,
so the tests check the command line and the copy without compiling the crate.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "benches" / "build_core.sh"

FAKE_CARGO = """#!/usr/bin/env bash
echo "$@" >> "$CARGO_CALLS"
mkdir -p "$CARGO_TARGET_DIR/release"
echo "built by: $*" > "$CARGO_TARGET_DIR/release/libpoisson_rs.so"
"""


@pytest.fixture
def fake_cargo(tmp_path: Path) -> dict[str, str]:
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    cargo = bin_dir / "cargo"
    cargo.write_text(FAKE_CARGO)
    cargo.chmod(0o755)
    env = dict(os.environ)
    env["PATH"] = f"{bin_dir}{os.pathsep}{env['PATH']}"
    env["CARGO_CALLS"] = str(tmp_path / "cargo_calls.txt")
    return env


def _git_available() -> bool:
    return (ROOT / ".git").exists()


def _run(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["bash", str(SCRIPT), *args], capture_output=True, text=True, env=env, timeout=120
    )


def _worktrees() -> str:
    return subprocess.run(
        ["git", "-C", str(ROOT), "worktree", "list", "--porcelain"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout


@pytest.mark.skipif(not _git_available(), reason="needs the package's git checkout")
@pytest.mark.parametrize("flag", [None, "--cargo"])
def test_builds_the_revision_and_puts_its_library_where_python_imports_it(
    tmp_path: Path, fake_cargo: dict[str, str], flag: str | None
) -> None:
    out = tmp_path / "base"
    try:
        done = _run(["HEAD", str(out)] + ([flag] if flag else []), fake_cargo)
        assert done.returncode == 0, done.stderr
        assert done.stdout.strip() == f"{out}/python"
        calls = Path(fake_cargo["CARGO_CALLS"]).read_text().splitlines()
        if flag is None:  # maturin's command: the cdylib alone
            expected = "rustc --quiet --profile release --features python --lib --crate-type cdylib"
        else:
            expected = "build --quiet --release --features python"
        assert calls == [expected]
        core = out / "python" / "poisson_rs" / "_core.abi3.so"
        assert core.read_text() == f"built by: {expected}\n"
        head = subprocess.run(
            ["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True
        ).stdout.strip()
        checked_out = subprocess.run(
            ["git", "-C", str(out), "rev-parse", "HEAD"], capture_output=True, text=True
        ).stdout.strip()
        assert checked_out == head
    finally:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(out)])


@pytest.mark.parametrize(
    "args, message",
    [
        ([], "usage:"),
        (["HEAD"], "usage:"),
        (["HEAD", "x", "--release"], "usage:"),
        (["not-a-revision-anywhere", "x"], "REV 'not-a-revision-anywhere' is not a commit"),
    ],
)
def test_bad_arguments_are_refused_before_any_build(
    tmp_path: Path, fake_cargo: dict[str, str], args: list[str], message: str
) -> None:
    if not _git_available() and "REV" in message:
        pytest.skip("needs the package's git checkout")
    done = _run([a if a != "x" else str(tmp_path / "x") for a in args], fake_cargo)
    assert done.returncode == 2
    assert message in done.stderr
    assert not Path(fake_cargo["CARGO_CALLS"]).exists()  # cargo never ran
    assert not (tmp_path / "x").exists()


@pytest.mark.skipif(not _git_available(), reason="needs the package's git checkout")
def test_an_existing_folder_is_left_as_it_is(tmp_path: Path, fake_cargo: dict[str, str]) -> None:
    out = tmp_path / "work"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    before = _worktrees()
    done = _run(["HEAD", str(out)], fake_cargo)
    assert done.returncode == 2
    assert f"DIR '{out}' exists" in done.stderr
    assert (out / "notes.txt").read_text() == "keep me"
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert _worktrees() == before  # no checkout was made
    assert not Path(fake_cargo["CARGO_CALLS"]).exists()
