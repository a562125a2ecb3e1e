"""Every bad input of tests/robustness_cases.py: exit 2 and one line ``error: <file>: <key>: <what> (got <value>)``.

Cases run in-process (``cli.main``) with file descriptor 2 captured, so Warp's native writes would
show too; a few also run as real ``softsim`` processes to prove the exit code and the absence of a
traceback from the outside.
"""

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import robustness_cases as rc  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
DOC = REPO / "docs" / "ROBUSTNESS.md"


def _check_answer(case, code, err):
    lines = err.splitlines()
    assert "Traceback" not in err, err
    assert len(lines) == 1, f"expected exactly one line on stderr, got:\n{err}"
    line = lines[0]
    assert code == case.code, line
    assert rc.LINE.match(line), f"not 'error: <file>: <key>: <what> (got <value>)': {line}"
    assert case.expect in line, line


@pytest.mark.parametrize("case", rc.CASES, ids=[c.id for c in rc.CASES])
def test_bad_input(case, tmp_path):
    got = rc.run_case(case, tmp_path)
    if got is None:
        pytest.skip("no directory here in which file creation is refused (not root, chmod ignored)")
    code, err = got
    _check_answer(case, code, err)


def test_base_scene_runs(tmp_path):
    """The unbroken base scene runs, so each case above fails because of its one edit."""
    base = rc.Case("base", "the valid base scene", "", args=(rc.SCENE, "--out", "base.usda"), code=0)
    code, err = rc.run_case(base, tmp_path)
    assert code == 0, err
    assert (tmp_path / "base.usda").is_file()


def test_debug_shows_traceback(tmp_path):
    case = next(c for c in rc.CASES if c.id == "dt_negative")
    debug = rc.Case(case.id, case.what, case.expect, case.edits, args=(rc.SCENE, "--debug"))
    code, err = rc.run_case(debug, tmp_path)
    assert code == 2
    assert "Traceback" in err and "SceneError" in err
    assert err.strip().splitlines()[-1].startswith("error: scene.toml: simulation.dt:")


@pytest.mark.parametrize("case_id", ["toml_missing_value", "flag_device_absent", "too_large", "out_parent_is_file"])
def test_bad_input_real_process(case_id, tmp_path):
    """A real ``softsim run`` process: exit 2, one line, no traceback, and no Warp banner or driver notice."""
    case = next(c for c in rc.CASES if c.id == case_id)
    argv = rc.prepare(case, tmp_path)
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "softsim_warp", *argv], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    elapsed = time.perf_counter() - t0
    _check_answer(case, proc.returncode, proc.stderr)
    assert proc.stdout == ""
    # Refusals happen before any simulation work: start-up (imports) dominates.
    assert elapsed < 30, f"took {elapsed:.1f} s"


def test_doc_table_matches(tmp_path):
    """docs/ROBUSTNESS.md lists exactly these cases with the answers they get now."""
    table = rc.markdown_table(rc.collect(tmp_path))
    doc = DOC.read_text()
    assert rc.DOC_BEGIN in doc and rc.DOC_END in doc
    assert rc.render_doc(doc, table) == doc, (
        "docs/ROBUSTNESS.md is out of date: run `python tests/robustness_cases.py --write docs/ROBUSTNESS.md`"
    )


def test_cases_are_distinct():
    ids = [c.id for c in rc.CASES]
    assert len(ids) == len(set(ids))
    assert all(os.sep not in i for i in ids)
