"""The command line: every number checked (finite, bounded, integer where needed) with one line on
stderr and exit status 2; outputs that would be replaced or misplaced refused before any work;
the subcommands registered from one list, and ``--help`` listing every one of them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import poisson_rs as pr
from poisson_rs import cli
from poisson_rs.cli import main
from poisson_rs.export import model_bytes
from poisson_rs.taylor import system_taylor_terms

SCENES = Path(__file__).resolve().parents[1] / "scenes"
PAPER = str(SCENES / "paper.toml")


def _one_line_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Runs the CLI: status 2 returned (not raised), one line on stderr."""
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, (argv, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1, (argv, err)
    assert "Traceback" not in err
    return lines[0]


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["demo", "--steps", "1e10"], "--steps"),  # bounded before numpy allocates anything
        (["demo", "--steps", "0"], "--steps"),
        (["demo", "--steps", "2.5"], "--steps"),
        (["demo", "--h", "nan"], "--h"),
        (["demo", "--h", "inf"], "--h"),
        (["demo", "--h", "0"], "--h"),
        (["demo", "--h", "1e400"], "--h"),
        (["demo", "--h", "10**400"], "--h"),
        (["stability", "--horizon", "1e300"], "--horizon"),
        (["stability", "--threshold", "-1"], "--threshold"),
        (["select", PAPER, "--T", "0"], "--T"),
        (["select", PAPER, "--max-steps", "0"], "--max-steps"),
        (["select", PAPER, "--budget", "nan"], "--budget"),
        (["select", PAPER, "--target", "0"], "--target"),
        (["chart", "--threads", "100000"], "--threads"),
        (["train", "--out", "x.safetensors", "--threads", "100000"], "--threads"),
        (["train", "--out", "x.safetensors", "--iterations", "-3"], "--iterations"),
        (["train", "--out", "x.safetensors", "--lr", "inf"], "--lr"),
        (["sweep", "--seeds", "1.5"], "--seeds"),
    ],
)
def test_every_number_is_checked_in_one_line(
    argv: list[str], says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert says in _one_line_exit_2(argv, capsys)


def test_demo_steps_are_bounded_by_the_memory_they_keep(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # 10⁹ steps pass the parser's bound, but the demo keeps every step of every method.
    line = _one_line_exit_2(["demo", "--steps", "1000000000", "--out", str(tmp_path / "o")], capsys)
    assert "GiB" in line and "steps fit" in line
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("command", ["demo", "chart", "stability", "sweep"])
def test_an_empty_output_folder_is_refused(
    command: str,
    capsys: pytest.CaptureFixture[str],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.chdir(tmp_path)
    assert "--out is empty" in _one_line_exit_2([command, "--out", ""], capsys)
    assert list(tmp_path.iterdir()) == []  # nothing written into the working directory


def test_a_web_address_is_not_a_scheduler(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["stability", "--quick", "--out", str(tmp_path / "o"), "--no-progress"]
    line = _one_line_exit_2([*argv, "--scheduler", "http://127.0.0.1:8787/status"], capsys)
    assert "web address" in line


def test_sweep_replot_of_a_file_that_is_not_a_sweep(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "rows.json"
    for content in ('[{"kind": "learned"}]', "{}", "[1, 2]", "[" * 100_000, "not json"):
        bad.write_text(content)
        line = _one_line_exit_2(
            ["sweep", "--out", str(tmp_path / "o"), "--replot", str(bad)], capsys
        )
        assert "--replot" in line
    missing = tmp_path / "none.json"
    _one_line_exit_2(["sweep", "--out", str(tmp_path / "o"), "--replot", str(missing)], capsys)


def _model(path: Path) -> None:
    system = pr.RigidBody()
    powers, coeffs = system_taylor_terms(system, 3, "cayley")
    path.write_bytes(
        model_bytes(
            powers=powers,
            coeffs=coeffs,
            layers=[],
            mlp_power=1,
            chart="cayley",
            system=system,
            h_max=1.0,
            domain={"kind": "all"},
            record={"name": "mine"},
        )
    )


def test_train_does_not_replace_a_model_without_force(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "m.safetensors"
    _model(out)
    before = out.read_bytes()
    argv = ["train", "--out", str(out), "--widths", "4", "--iterations", "2", "--no-progress"]
    assert "--force" in _one_line_exit_2(argv, capsys)
    assert out.read_bytes() == before
    check = tmp_path / "c.ckpt"
    check.write_bytes(b"another run's checkpoint")
    fresh = ["train", "--out", str(tmp_path / "n.safetensors"), "--checkpoint", str(check)]
    assert "--checkpoint" in _one_line_exit_2([*fresh, "--iterations", "2"], capsys)
    assert check.read_bytes() == b"another run's checkpoint"
    assert main([*argv, "--force", "--threads", "1"]) == 0
    assert out.read_bytes() != before and pr.load_model(out).metadata["name"] == "m"


def test_help_lists_every_subcommand_without_markup(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    for name in ("demo", "train", "models", "chart", "stability", "select", "sweep"):
        assert f"    {name}" in text, name
    assert "``" not in text


def test_subcommands_come_from_one_list_and_an_absent_module_is_skipped(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    assert "poisson_rs.learn.cli" in cli.COMMANDS  # joins once it exists
    monkeypatch.setattr(cli, "COMMANDS", (*cli.COMMANDS, "poisson_rs.no_such_module.cli"))
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert set(sub.choices) >= {"demo", "train", "select", "sweep"}
    for name in ("demo", "chart", "stability", "select", "sweep", "models", "train"):
        module = __import__(f"poisson_rs.cli.{name}", fromlist=["run"])
        assert callable(module.add_parser) and callable(module.run)


def test_select_json_rows_name_their_metric(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "rows.json"
    argv = ["select", PAPER, "--target", "1e-3", "--metric", "energy", "--T", "1"]
    assert main([*argv, "--budget", "2", "--models", "default", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())
    assert {r["metric"] for r in rows} == {"energy"}
    assert "selected for energy <= 1e-03" in capsys.readouterr().out


def test_train_reports_the_lbfgs_polish(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "m.safetensors"
    argv = ["train", "--out", str(out), "--widths", "4", "--iterations", "3"]
    assert main([*argv, "--lbfgs-iterations", "2", "--no-progress", "--threads", "1"]) == 0
    text = capsys.readouterr().out
    assert "L-BFGS polish of up to 2 iterations" in text
    assert "L-BFGS polish: " in text and " -> " in text
