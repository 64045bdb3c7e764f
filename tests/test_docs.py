"""The manual cannot drift: the generated reference is current, every documented command runs.

``docs/configuration.md`` is what ``docs/gen_config.py`` writes from the
configuration's own help texts; every ``rangeseg`` command in a ``sh`` block of
README.md and docs/*.md runs (exit code 0) in a scratch folder beside the
repository's ``sample_data`` and ``docs``, in the order the page gives them,
except the few that need a network service, named in :data:`NOT_RUN` with the
reason.
"""

from __future__ import annotations

import importlib.util
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
RANGESEG = Path(sys.executable).with_name("rangeseg")

#: Documented commands that are not run here: (page, command prefix) -> why.
NOT_RUN: dict[tuple[str, str], str] = {
    ("docs/cli.md", "rangeseg run s3://bucket/frames -o s3://bucket/results"):
        "needs an S3 bucket (tests/test_storage.py runs the same on a local moto server)",
    ("docs/cli.md", "rangeseg run s3://bucket/frames -o out/results"):
        "needs an S3 bucket (tests/test_storage.py)",
    ("docs/cli.md", "rangeseg grow s3://bucket/results"):
        "needs an S3 bucket (tests/test_storage.py)",
    ("docs/cli.md", "rangeseg run /shared/scans -o /shared/out --executor dask"):
        "needs a Dask scheduler at tcp://HOST:8786 (tests/test_dask.py runs a LocalCluster)",
}


def _gen_config():
    spec = importlib.util.spec_from_file_location("gen_config", ROOT / "docs" / "gen_config.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_configuration_reference_is_what_gen_config_writes():
    gen = _gen_config()
    committed = (ROOT / "docs" / "configuration.md").read_text(encoding="utf-8")
    assert committed == gen.render(), "docs/configuration.md is stale: run docs/gen_config.py"


def test_configuration_reference_names_every_key():
    from rangeseg_cli.config import key_reference

    text = (ROOT / "docs" / "configuration.md").read_text(encoding="utf-8")
    for ref in key_reference():
        assert f"`{ref.key} = " in text
        assert ref.help in text


def sh_commands(page: Path) -> list[str]:
    """The commands of a page's ``sh`` blocks, continuation lines joined, comments dropped."""
    out = []
    for block in re.findall(r"^ *```sh\n(.*?)^ *```", page.read_text(encoding="utf-8"),
                            flags=re.S | re.M):
        for line in block.replace("\\\n", " ").splitlines():
            words = shlex.split(line, comments=True)
            if words:
                out.append(shlex.join(words))
    return out


def _not_run(page: Path, command: str) -> str | None:
    name = page.relative_to(ROOT).as_posix()
    for (where, prefix), reason in NOT_RUN.items():
        if where == name and command.startswith(prefix):
            return reason
    return None


def test_every_not_run_command_is_in_its_page_and_needs_the_network():
    for (where, prefix), reason in NOT_RUN.items():
        commands = sh_commands(ROOT / where)
        assert any(c.startswith(prefix) for c in commands), f"{where}: no {prefix!r}"
        assert "s3://" in prefix or "--executor dask" in prefix, prefix
        assert reason


def test_the_readme_shows_rangeseg_commands():
    commands = sh_commands(ROOT / "README.md")
    assert sum(c.startswith("rangeseg ") for c in commands) >= 10


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_documented_rangeseg_command_runs(page, tmp_path):
    commands = [c for c in sh_commands(page) if c.startswith("rangeseg ")]
    if not commands:
        return  # a page without commands
    for name in ("sample_data", "docs"):
        (tmp_path / name).symlink_to(ROOT / name)
    for command in commands:
        if _not_run(page, command):
            continue
        args = shlex.split(command)
        done = subprocess.run([str(RANGESEG), *args[1:], *(["-q"] if _batch(args) else [])],
                              cwd=tmp_path, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, f"{page.name}: {command}\n{done.stderr[-2000:]}"
    for command in sh_commands(page):  # files the pages show with cat exist after the commands
        if command.startswith("cat "):
            assert (tmp_path / shlex.split(command)[1]).is_file(), command


def _batch(args: list[str]) -> bool:
    return args[1] in {"run", "edges", "link", "grow", "holdsite", "synth", "eval"}


def test_rangeseg_config_cites_the_docs_and_says_what_it_shows():
    from click.testing import CliRunner

    from rangeseg_cli.cli.main import main

    defaults = CliRunner().invoke(main, ["config"])
    assert defaults.exit_code == 0
    assert "SPEC" not in defaults.output
    assert "docs/configuration.md" in defaults.output
    assert "the defaults" in defaults.output.splitlines()[0]
    changed = CliRunner().invoke(main, ["config", "--preset", "mm-depth", "--set",
                                        "step.threshold=2"])
    assert changed.exit_code == 0
    header = "\n".join(changed.output.splitlines()[:3])
    assert "the defaults (" not in header
    assert "--preset mm-depth" in header and "--set step.threshold=2" in header
    assert "default 6.0" in changed.output  # the changed key says its default
    assert "SPEC" not in changed.output


def test_performance_page_is_what_the_benchmark_results_give():
    spec = importlib.util.spec_from_file_location("report", ROOT / "benchmarks" / "report.py")
    assert spec is not None and spec.loader is not None
    report = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(report)
    committed = (ROOT / "docs" / "performance.md").read_text(encoding="utf-8")
    assert committed == report.render(), "docs/performance.md is stale: run benchmarks/report.py"


@pytest.mark.parametrize("page", [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))],
                         ids=lambda p: p.relative_to(ROOT).as_posix())
def test_no_page_is_longer_than_its_budget(page):
    words = len(page.read_text(encoding="utf-8").split())
    assert words <= (2000 if page.name == "README.md" else 3000), f"{page.name}: {words} words"
