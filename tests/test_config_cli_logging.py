"""Configuration, the command line and the logging bridge."""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import pytest

import dhptam
from dhptam import Config
from dhptam import logs as dlogs
from dhptam.cli import main

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    tomllib = None  # type: ignore[assignment]


def test_defaults_are_documented_and_round_trip():
    text = Config.defaults_toml()
    assert Config.from_toml(text) == Config()
    for section in ("[log]", "[rectification]", "[triangulation]"):
        assert section in text
    # Every key is preceded by at least one comment line.
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if "=" in line and not line.startswith("#"):
            assert lines[i - 1].startswith("#"), f"undocumented key: {line}"


def test_unknown_key_and_bad_value_name_the_key():
    with pytest.raises(dhptam.ConfigError, match="min_dept_m"):
        Config.from_toml("[triangulation]\nmin_dept_m = 1.0\n")
    with pytest.raises(dhptam.ConfigError, match=r"rectification\.balance"):
        Config.from_toml("[rectification]\nbalance = -1\n", "mine.toml")


def test_missing_file_is_a_file_error(tmp_path):
    missing = tmp_path / "nope.toml"
    with pytest.raises(dhptam.FileError) as info:
        Config.from_file(missing)
    assert info.value.path == str(missing)
    assert isinstance(info.value, OSError)


def test_to_dict_reflects_values():
    config = Config.from_toml("[triangulation]\nmin_depth_m = 0.25\n")
    assert config.to_dict()["triangulation"]["min_depth_m"] == 0.25
    assert config.to_dict()["log"]["level"] == "info"


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "dhptam", *args], capture_output=True, text=True, check=False
    )


def test_cli_version_and_defaults():
    version = run_cli("--version")
    assert version.returncode == 0 and dhptam.__version__ in version.stdout
    defaults = run_cli("config", "--defaults")
    assert defaults.returncode == 0
    assert Config.from_toml(defaults.stdout) == Config()
    if tomllib is not None:
        assert "triangulation" in tomllib.loads(defaults.stdout)


def test_cli_check_reports_bad_file_without_traceback(tmp_path: Path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[rectification]\nbalanse = 0.5\n")
    result = run_cli("config", "--check", str(bad))
    assert result.returncode == 2
    assert "balanse" in result.stderr and str(bad) in result.stderr
    assert "Traceback" not in result.stderr
    good = tmp_path / "good.toml"
    good.write_text("[rectification]\nbalance = 0.5\n")
    result = run_cli("config", "--check", str(good))
    assert result.returncode == 0 and "balance = 0.5" in result.stdout


def test_cli_usage_errors_exit_2(capsys):
    assert main([]) == 2
    with pytest.raises(SystemExit) as info:
        main(["no-such-command"])
    assert info.value.code == 2


def test_rust_log_records_reach_python_logging(caplog, monkeypatch):
    monkeypatch.delenv(dlogs.ENV_VAR, raising=False)
    caplog.set_level(logging.DEBUG, logger="dhptam_core")
    dlogs.configure("info", handler=logging.NullHandler())
    dhptam._core._log_from_rust("info", "hello from rust")
    dhptam._core._log_from_rust("debug", "hidden at info")
    messages = [(r.name, r.levelno, r.getMessage()) for r in caplog.records]
    assert ("dhptam_core", logging.INFO, "hello from rust") in messages
    assert all(m != "hidden at info" for _, _, m in messages)


def test_environment_variable_overrides_the_level(caplog, monkeypatch):
    monkeypatch.setenv(dlogs.ENV_VAR, "debug")
    assert dlogs.configure("warn", handler=logging.NullHandler()) == logging.DEBUG
    caplog.set_level(logging.DEBUG, logger="dhptam_core")
    dhptam._core._log_from_rust("debug", "now visible")
    assert any(r.getMessage() == "now visible" for r in caplog.records)
    monkeypatch.setenv(dlogs.ENV_VAR, "loud")
    with pytest.raises(dhptam.ConfigError, match="DHPTAM_LOG"):
        dlogs.configure()


def test_level_from_config(monkeypatch):
    monkeypatch.delenv(dlogs.ENV_VAR, raising=False)
    config = Config.from_toml('[log]\nlevel = "warn"\n')
    assert dlogs.resolve_level(config=config) == logging.WARNING


@pytest.fixture
def fresh_loggers():
    """The dhptam loggers as a new process has them (no level, no handler), put back as they
    were after the test."""
    saved = [(logging.getLogger(n), logging.getLogger(n).level, list(logging.getLogger(n).handlers))
             for n in dlogs.LOGGER_NAMES]  # fmt: skip
    for logger, _, handlers in saved:
        logger.setLevel(logging.NOTSET)
        for h in handlers:
            logger.removeHandler(h)
    dhptam._core._reset_log_cache()
    yield
    for logger, level, handlers in saved:
        logger.setLevel(level)
        logger.handlers[:] = handlers
    dhptam._core._reset_log_cache()


def _levels_in(log: Path) -> set[str]:
    return {line.split()[2] for line in log.read_text().splitlines() if len(line.split()) > 2}


def test_run_log_takes_the_level_asked_for(sim_desk_run, tmp_path, monkeypatch, capsys, fresh_loggers):
    run = ["run", "--sequence", str(sim_desk_run), "--features", "orb", "--max-frames", "6", "-q", "--sync"]
    # By default run.log holds INFO and above, and the console only what goes wrong.
    monkeypatch.delenv(dlogs.ENV_VAR, raising=False)
    assert main([*run, "--out", str(tmp_path / "default")]) == 0
    assert "INFO" in _levels_in(tmp_path / "default" / "run.log")
    assert "DEBUG" not in _levels_in(tmp_path / "default" / "run.log")
    assert "INFO" not in capsys.readouterr().err
    # [log] level = "debug" in the run's configuration: run.log gets the Rust core's debug lines.
    config = tmp_path / "debug.toml"
    config.write_text('[log]\nlevel = "debug"\n')
    assert main([*run, "--config", str(config), "--out", str(tmp_path / "config")]) == 0
    lines = (tmp_path / "config" / "run.log").read_text().splitlines()
    assert any(" DEBUG dhptam_core" in line for line in lines), "no debug record from the Rust core"
    # DHPTAM_LOG=debug does the same without a config file, and shows the level on the console.
    monkeypatch.setenv(dlogs.ENV_VAR, "debug")
    assert main([*run, "--out", str(tmp_path / "env")]) == 0
    assert "DEBUG" in _levels_in(tmp_path / "env" / "run.log")
    assert " DEBUG dhptam_core" in capsys.readouterr().err
    # A level the loggers do not know is a usage error naming the variable.
    monkeypatch.setenv(dlogs.ENV_VAR, "loud")
    assert main([*run, "--out", str(tmp_path / "bad")]) == 2
    assert "DHPTAM_LOG" in capsys.readouterr().err
