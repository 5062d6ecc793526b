"""The docs site (mkdocs.yml): it builds with --strict, every command and method has a reference
page, and a reference page shows the config dataclass's default (the one source of defaults)."""

import dataclasses
import os
import re
import shutil
import subprocess
import sys

import pytest

from tests.conftest import REPO

pytest.importorskip("mkdocs", reason="mkdocs is not installed (pip install -e '.[docs]')")
pytest.importorskip(
    "material", reason="mkdocs-material is not installed (pip install -e '.[docs]')"
)


def build(root, out) -> subprocess.CompletedProcess:
    """`mkdocs build --strict` of root/mkdocs.yml into `out` (never --quiet: it hides the
    warnings that --strict counts)."""
    return subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(out)],
        cwd=root,
        check=False,  # the callers assert on the return code and show mkdocs's message
        capture_output=True,
        text=True,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    out = tmp_path_factory.mktemp("site")
    done = build(REPO, out)
    assert done.returncode == 0, done.stderr
    return out


def default_on_page(page, name: str) -> str:
    """The default column of the options-table row whose first cell is `name`."""
    html = page.read_text(encoding="utf-8")
    row = re.search(
        rf"<td><code>{re.escape(name)}</code></td>\s*<td>.*?</td>\s*<td><code>([^<]*)</code></td>",
        html,
    )
    assert row, f"no row for {name} in {page}"
    return row.group(1)


def field_default(cls, name: str):
    return {f.name: f.default for f in dataclasses.fields(cls)}[name]


def test_every_command_and_method_has_a_reference_page(site):
    from recon.cli.main import COMMANDS
    from recon.models.registry import METHOD_NAMES

    for name in COMMANDS:
        assert (site / "reference" / name / "index.html").is_file(), name
    for name in METHOD_NAMES:
        assert (site / "reference" / "methods" / name / "index.html").is_file(), name
    # made in memory at build time: nothing generated is left under docs/
    assert not (REPO / "docs" / "reference").exists()


def test_a_command_page_shows_the_config_default(site):
    from recon.eval.stage import EvalConfig

    shown = default_on_page(site / "reference" / "eval" / "index.html", "--border")
    assert float(shown) == field_default(EvalConfig, "border") == 0.15


def test_a_method_page_shows_the_config_default(site):
    from recon.models.registry import method_spec

    config = method_spec("3dgs").config_cls
    shown = default_on_page(site / "reference" / "methods" / "3dgs" / "index.html", "sh_degree")
    assert int(shown) == field_default(config, "sh_degree")


def test_a_broken_link_fails_the_build(tmp_path):
    shutil.copy(REPO / "mkdocs.yml", tmp_path)
    shutil.copytree(REPO / "docs", tmp_path / "docs", ignore=shutil.ignore_patterns("__pycache__"))
    with open(tmp_path / "docs" / "index.md", "a", encoding="utf-8") as page:
        page.write("\n[a page that is not there](no-such-page.md)\n")
    done = build(tmp_path, tmp_path / "site")
    assert done.returncode != 0
    assert "no-such-page.md" in done.stderr
