"""The manual (docs/, README.md): generated pages in step with the code, the README short and its quick
start as .ci/run and the tutorial rely on, and user-facing pages free of tracker and scratch references.

The strict site build (``mkdocs build --strict``: broken links, pages missing from the nav) runs in .ci/run.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"


def _gen_docs():
    spec = importlib.util.spec_from_file_location("gen_docs", ROOT / "tools" / "gen_docs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_generated_pages_are_up_to_date():
    assert _gen_docs().stale_pages() == [], "run: python tools/gen_docs.py"


def test_a_stale_page_is_caught(tmp_path):
    gen = _gen_docs()
    for page in gen.PAGES:
        (tmp_path / page).write_text((DOCS / page).read_text())
    cli = tmp_path / "cli.md"
    cli.write_text(cli.read_text().replace("| `--legs LEGS` |", "| `--legs N` |", 1))
    assert gen.stale_pages(tmp_path) == ["cli.md"]


def test_every_mission_key_is_documented_with_its_default():
    from passt_mav.mission.config import GPConfig, MissionConfig, PlannerConfig

    text = (DOCS / "missions.md").read_text()
    for prefix, cls in (("", MissionConfig), ("gp.", GPConfig), ("planner.", PlannerConfig)):
        for name in cls.model_fields:
            assert f"| `{prefix}{name}` |" in text, f"{prefix}{name}"
    row = next(line for line in text.splitlines() if line.startswith("| `gp.prior_share` |"))
    assert f"`{GPConfig().prior_share}`" in row


def test_readme_is_short_and_keeps_the_quick_start():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 150
    # .ci/run and the session's stop hook run these two lines as written
    assert "python3 -m venv .venv && .venv/bin/pip install -e . && .venv/bin/passt-mav demo\n" in text
    assert "python3 -m venv .venv && .venv/bin/pip install -e '.[test]' && .venv/bin/python -m pytest -q\n" in text
    for link in re.findall(r"\]\((docs/[^)#]+)", text):
        assert (ROOT / link).is_file(), link


def test_user_pages_name_no_issues_sessions_or_scratch_paths():
    pages = [ROOT / "README.md", *(p for p in DOCS.glob("*.md"))]
    # an issue's item ("item 3"), not a mission's ("at item 3/5"); a dated session ("session 41"), not summary.json's sessions
    bad = re.compile(r"\bissue \d+|\bitem \d+(?![/\d])|/tmp/|\bsessions? \d+|\bH[12]00\b", re.IGNORECASE)
    hits = [f"{p.name}: {m.group(0)}" for p in pages for m in bad.finditer(p.read_text())]
    assert hits == []
