"""Hostile scene input: deep nesting, odd Unicode keys, huge numbers, odd files.

Every case must end as a :class:`SceneError` (one line, ``<file>: <key>: <what> (got <value>)``)
and never as another exception: before these tests a 10000-deep array was a RecursionError, and
``--set jelly.²=1`` a ValueError from ``int('²')``. No case here runs a simulation; the errors
come before any work.
"""

import math
import os
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from softsim_warp.commands import cli
from softsim_warp.core.errors import SceneError
from softsim_warp.io import scene

sys.path.insert(0, str(Path(__file__).parent))
import robustness_cases as rc  # noqa: E402

BASE = tomllib.loads(rc.BASE)
DEEP = 10000


def _one_line(err: SceneError) -> str:
    line = "error: " + err.line()
    assert "\n" not in line and "\r" not in line
    assert rc.LINE.match(line), line
    # Keys and values are cut short (the file part is the path as given).
    assert len(line) - len(err.source) < 1000, line[:300]
    return line


def _refused(fn, *args, **kw) -> str:
    with pytest.raises(SceneError) as info:
        fn(*args, **kw)
    return _one_line(info.value)


def _base(**jelly):
    d = tomllib.loads(rc.BASE)
    d["jelly"][0].update(jelly)
    return d


def _nest(depth, leaf=1, kind="list"):
    v = leaf
    for i in range(depth):
        v = [v] if kind == "list" or (kind == "mixed" and i % 2) else {"a": v}
    return v


# --- deep nesting -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "opener, closer",
    [("[", "]"), ("{a=", "}"), ("[{a=", "}]"), ("{a=[", "]}")],
    ids=["arrays", "inline_tables", "mixed", "mixed2"],
)
@pytest.mark.parametrize("depth", [101, 500, DEEP])
def test_deep_toml_is_one_line(opener, closer, depth):
    text = rc.BASE.replace("resolution = [3, 3, 3]", "resolution = " + opener * depth + "1" + closer * depth)
    line = _refused(scene.parse_toml, text, "deep.toml")
    assert line.startswith("error: deep.toml: line 11, column ")
    assert "nested deeper than 100 levels" in line
    assert "resolution = " in line


def test_nesting_at_the_limit_parses_and_fails_validation():
    text = rc.BASE.replace("resolution = [3, 3, 3]", "resolution = " + "[" * 100 + "1" + "]" * 100)
    data = scene.parse_toml(text, "deep.toml")
    line = _refused(scene.validate, data, "deep.toml")
    assert "jelly.0.resolution: must be an integer >= 1" in line


def test_brackets_in_strings_and_comments_are_not_nesting():
    many = "[{" * 300
    text = rc.BASE.replace('name = "base"', f"name = \"{many}\"\n# {many}\ndescription2 = '{many}'")
    text = text.replace('description = "robustness base scene"', f'description = """{many}\n{many}"""')
    assert scene.nesting_overflow(text) is None
    data = scene.parse_toml(text, "s.toml")
    assert data["name"] == many


def test_nesting_overflow_counts_levels():
    assert scene.nesting_overflow("v = " + "[" * 100 + "]" * 100) is None
    assert scene.nesting_overflow("v = " + "[" * 101 + "]" * 101) == 4 + 100
    assert scene.nesting_overflow("[a]\n" * 1000) is None  # many tables, none nested


@pytest.mark.parametrize("raw", ["[" * DEEP + "1" + "]" * DEEP, "[" * DEEP, "{a=" * DEEP + "1" + "}" * DEEP])
def test_deep_set_value_is_one_line(raw):
    line = _refused(scene.parse_override, f"jelly.0.resolution={raw}")
    assert line.startswith("error: command line: --set jelly.0.resolution: arrays and inline tables nested deeper")


@pytest.mark.parametrize("kind", ["list", "dict", "mixed"])
def test_deep_dict_scene_is_one_line(kind):
    line = _refused(scene.scene_from_dict, _base(resolution=_nest(DEEP, kind=kind)), source="api")
    assert line.startswith("error: api: jelly.0.resolution.")
    assert "nested deeper than 100 levels" in line


def test_cyclic_dict_scene_is_one_line():
    d = _base()
    d["jelly"][0]["resolution"] = cyc = []
    cyc.append(cyc)
    assert "nested deeper than 100 levels" in _refused(scene.scene_from_dict, d)
    d = _base()
    d["simulation"]["loop"] = d
    assert "nested deeper than 100 levels" in _refused(scene.scene_from_dict, d)


def test_deep_value_given_to_validate_directly_is_shown_bounded():
    """validate() without scene_from_dict's copy: the message still formats a 10000-deep value."""
    d = _base()
    d["simulation"]["zzz"] = _nest(DEEP, kind="mixed")
    line = _refused(scene.validate, d, "s.toml")
    assert "simulation.zzz: unknown key" in line


def test_deep_key_path_from_set():
    doc = tomllib.loads(rc.BASE)
    line = _refused(scene.parse_override, ".".join(["a"] * 10000) + "=1")
    assert "at most 16 parts" in line
    k, v = scene.parse_override(".".join(["a"] * 16) + "=1")
    scene.apply_override(doc, k, v)
    assert "a: unknown key" in _refused(scene.validate, doc, "s.toml")


# --- Unicode keys and list indices ------------------------------------------------------------

# Superscripts, Arabic-Indic, Persian, Devanagari, fullwidth and mathematical digits, a combining
# mark, roman numerals, fractions; and ASCII that int() reads but an index is not.
ODD_INDICES = ["²", "¹", "٣", "٠", "۴", "०", "０", "1\u0301", "\u0661\u0662", "Ⅷ", "½", "𝟙"]
ODD_INDICES += ["1 ", " 1", "+1", "-1", "0x1", "1_0"]


@pytest.mark.parametrize("part", ODD_INDICES)
def test_odd_index_in_set_is_one_line(part):
    doc = tomllib.loads(rc.BASE)
    key, value = scene.parse_override(f"jelly.{part}.size=1")
    line = _refused(scene.apply_override, doc, key, value)
    assert "--set jelly." in line and "expected an index (digits 0-9); the scene has 1 jelly table" in line
    line = _refused(scene.apply_override, doc, f"jelly.{part}", 1)
    assert "expected an index" in line


@pytest.mark.parametrize("part", ["²", "٣", "０"])
def test_odd_index_after_missing_table_is_a_key_not_an_index(part):
    doc = tomllib.loads(rc.BASE)
    scene.apply_override(doc, f"bowl.{part}.radius", 1)  # not an index: a table named part
    assert "unknown key" in _refused(scene.validate, doc, "s.toml")


def test_ascii_indices_still_work():
    doc = tomllib.loads(rc.BASE)
    scene.apply_overrides(doc, [scene.parse_override(s) for s in ("jelly.0.resolution.1=4", "jelly.000.size=0.25")])
    assert doc["jelly"][0]["resolution"] == [3, 4, 3] and doc["jelly"][0]["size"] == 0.25
    line = _refused(scene.apply_override, doc, "jelly.0.resolution.3", 1)
    assert "--set jelly.0.resolution.3: index out of range; the list has 3 entries" in line
    line = _refused(scene.apply_override, doc, "jelly." + "9" * 5000 + ".size", 1)
    assert "index out of range; the scene has 1 jelly table" in line


@pytest.mark.parametrize(
    "item",
    ["jelly..size=1", "=1", "...=1", ".=1", " =1", "jelly.0.=1", ".jelly=1", " . =1", "=", "==1"],
)
def test_malformed_set_keys(item):
    assert "command line: --set: expected" in _refused(scene.parse_override, item)


@pytest.mark.parametrize("item", [None, 3, ("jelly.0.size", 1), b"simulation.dt=1"])
def test_parse_override_of_a_non_string(item):
    assert "command line: --set: expected KEY=VALUE text" in _refused(scene.parse_override, item)
    assert "--set: expected KEY=VALUE text" in _refused(scene.load_scene, "jelly_drop", [item])


@pytest.mark.parametrize("key", ["", None, 3, ("a",), "a..b", "." * 5])
def test_apply_override_with_a_bad_key(key):
    assert "--set: expected a dotted key" in _refused(scene.apply_override, tomllib.loads(rc.BASE), key, 1)


@pytest.mark.parametrize(
    "name",
    ["²", "ü", "a\u0301", "\u200b", "a\x00b", "a:b", "a\nb", "\udcff", "x" * 100000, "٣"],
    ids=["superscript", "umlaut", "combining", "zero_width", "nul", "colon", "newline", "surrogate", "long", "arabic"],
)
def test_odd_unicode_keys_are_unknown_keys(name):
    doc = tomllib.loads(rc.BASE)
    doc["jelly"][0][name] = 1
    line = _refused(scene.validate, doc, "s.toml")
    assert "jelly.0." in line and "unknown key" in line
    # the same from --set
    doc = tomllib.loads(rc.BASE)
    k, v = scene.parse_override(f"simulation.{name}=1")
    scene.apply_override(doc, k, v)
    assert "unknown key" in _refused(scene.validate, doc, "s.toml")


@pytest.mark.parametrize(
    "key",
    [1, None, True, 2.5, math.nan, ("a", 1), 10**5000, b"dt", frozenset()],
    ids=["int", "none", "bool", "float", "nan", "tuple", "huge_int", "bytes", "frozenset"],
)
def test_non_string_keys_are_unknown_keys(key):
    d = _base()
    d["simulation"][key] = 1
    line = _refused(scene.scene_from_dict, d, source="api")
    assert line.startswith("error: api: simulation.") and "unknown key; allowed: integrator" in line
    d = _base()
    d[key] = 1
    assert "unknown key" in _refused(scene.scene_from_dict, d, source="api")


def test_surrogate_text_is_refused():
    """Undecodable bytes in an argument arrive as lone surrogates, which no file or USD can hold."""
    doc = tomllib.loads(rc.BASE)
    scene.apply_override(doc, *scene.parse_override("name=\udcff"))
    assert "name: must be valid Unicode text" in _refused(scene.validate, doc, "s.toml")


# --- numbers ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "where, value, expect",
    [
        (("simulation", "dt"), 10**400, "simulation.dt: must be a finite number > 0"),
        (("simulation", "dt"), -(10**400), "simulation.dt: must be a finite number > 0"),
        (("simulation", "dt"), 10**5000, "simulation.dt: must be a finite number > 0 (got <integer of"),
        (("simulation", "frames"), 10**400, "simulation.frames: must be an integer >= 1 and below 2^63"),
        (("simulation", "frames"), 2**63, "simulation.frames: must be an integer >= 1 and below 2^63"),
        (("simulation", "gravity"), [0, 10**400, 0], "simulation.gravity: must be a list of 3 finite numbers"),
        (("jelly", 0, "resolution"), 10**400, "jelly.0.resolution: must be an integer >= 1 or a list of 3 such"),
        (("jelly", 0, "resolution"), [3, 3, 2**63], "each below 2^63"),
        (("jelly", 0, "size"), 10**400, "jelly.0.size: must be a list of 3 finite numbers or one number"),
        (("jelly", 0, "size"), math.inf, "jelly.0.size: must be a list of 3 finite numbers or one number"),
        (("simulation", "integrator"), np.array(["rk4", "euler"]), "simulation.integrator: must be one of"),
        (("simulation", "integrator"), ["rk4"], "simulation.integrator: must be one of"),
    ],
    ids=["dt_huge", "dt_huge_negative", "dt_5000_digits", "frames_huge", "frames_2_63", "gravity_huge", "res_huge",
         "res_2_63", "size_huge", "size_inf", "integrator_ndarray", "integrator_list"],
)
def test_huge_and_odd_numbers(where, value, expect):
    d = _base()
    node = d
    for k in where[:-1]:
        node = node[k]
    node[where[-1]] = value
    if where[-1] == "frames":
        d["simulation"].pop("duration", None)
    assert expect in _refused(scene.scene_from_dict, d)


def test_int_below_2_63_is_an_integer():
    class Ctx:
        def fail(self, *a):  # pragma: no cover - must not be called
            raise AssertionError(a)

    assert scene.Int(lo=1).check(2**63 - 1, "k", Ctx()) == 2**63 - 1


def test_value_whose_str_fails_is_shown():
    class Bad:
        def __str__(self):
            raise RuntimeError("no")

    line = _refused(scene.scene_from_dict, _base(size=Bad()))
    assert "jelly.0.size: must be" in line and "(got <Bad>)" in line


@pytest.mark.parametrize(
    "text, expect",
    [
        ("frames = " + "9" * 5000, "line 7, column 10: number too long: an integer may have at most"),
        ("frames = 0x" + "f" * 5000, "frames: must be an integer >= 1 and below 2^63 (got <integer of 20000 bits>)"),
        ("frames = " + "9" * 400, "simulation.frames: must be an integer >= 1 and below 2^63"),
        ("frames = 1e999", "simulation.frames: must be an integer >= 1 (got inf)"),
        ("frames = -1e999", "simulation.frames: must be an integer >= 1 (got -inf)"),
    ],
)
def test_huge_numbers_in_toml(text, expect):
    source = rc.BASE.replace("frames = 2", text)
    line = _refused(lambda: scene.validate(scene.parse_toml(source, "s.toml"), "s.toml"))
    assert expect in line


@pytest.mark.parametrize(
    "raw, expect",
    [
        ("9" * 5000, "--set simulation.frames: number too long"),
        ("9" * 400, "simulation.frames: must be an integer >= 1 and below 2^63"),
        ("1e999", "simulation.frames: must be an integer >= 1 (got inf)"),
        ("3\nfps = 1", "simulation.frames: must be an integer >= 1 (got '3\\nfps = 1')"),
        ("0x" + "f" * 5000, "--set simulation.frames: number too long"),
    ],
)
def test_huge_numbers_in_set(raw, expect):
    def load():
        doc = tomllib.loads(rc.BASE)
        scene.apply_overrides(doc, [scene.parse_override(f"simulation.frames={raw}")])
        scene.validate(doc, "s.toml")

    assert expect in _refused(load)


# --- files ------------------------------------------------------------------------------------


def test_scene_path_that_is_a_fifo(tmp_path):
    fifo = tmp_path / "pipe.toml"
    os.mkfifo(fifo)
    assert "scene: is not a regular file" in _refused(scene.read_scene_data, str(fifo))


def test_scene_path_that_is_a_device():
    assert "scene: is not a regular file" in _refused(scene.read_scene_data, "/dev/zero")


def test_scene_path_with_nul():
    line = _refused(scene.read_scene_data, "a\0b.toml")
    assert line.startswith("error: a\\0b.toml: scene: a file name cannot contain a NUL character")


def test_scene_path_too_long():
    for name in ("a" * 5000, "a" * 5000 + ".toml", "d/" + "a" * 5000):
        line = _refused(scene.read_scene_data, name)
        assert "scene: " in line


def test_scene_file_too_large(tmp_path):
    big = tmp_path / "big.toml"
    with open(big, "wb") as f:
        f.truncate(scene.MAX_SCENE_BYTES + 1)  # sparse: nothing is written
    assert "scene: file too large for a scene" in _refused(scene.read_scene_data, str(big))


def test_scene_file_not_utf8(tmp_path):
    p = tmp_path / "s.toml"
    p.write_bytes(rc.BASE.encode().replace(b"base", b"\xc3\x28", 1))
    assert "line 1: TOML files must be UTF-8 text" in _refused(scene.read_scene_data, str(p))


# --- end to end: softsim run, in-process ------------------------------------------------------


def _cli(argv, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ok.toml").write_text(rc.BASE)
    code = cli.main(argv if argv[0] == "compare" else ["run", *argv, "--quiet"])
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    lines = err.splitlines()
    assert len(lines) == 1, err[:2000]
    assert code == 2, lines[0]
    assert lines[0].startswith("error: ") and rc.LINE.match(lines[0]), lines[0][:500]
    return lines[0]


DEEP_RES = "[" * DEEP + "1" + "]" * DEEP


@pytest.mark.parametrize(
    "args, expect",
    [
        (["ok.toml", "--set", f"jelly.0.resolution={DEEP_RES}"], "command line: --set jelly.0.resolution: arrays"),
        (["ok.toml", "--set", "jelly.²=1"], 'command line: --set jelly."\\u00b2": expected an index'),
        (["ok.toml", "--set", "jelly.٣.size=1"], 'command line: --set jelly."\\u0663": expected an index'),
        (["ok.toml", "--set", "jelly.٠.size=1"], 'command line: --set jelly."\\u0660": expected an index'),
        (["ok.toml", "--set", "jelly..size=1"], "command line: --set: expected a dotted key"),
        (["ok.toml", "--set", "=1"], "command line: --set: expected a dotted key"),
        (["ok.toml", "--set", "...=1"], "command line: --set: expected a dotted key"),
        (["ok.toml", "--set", "jelly.0.si\0ze=1"], 'ok.toml: jelly.0."si\\u0000ze": unknown key'),
        (["ok.toml", "--set", "jelly.0.resolution=" + "9" * 5000], "--set jelly.0.resolution: number too long"),
        (["ok.toml", "--set", "jelly.0.resolution=" + "9" * 400], "jelly.0.resolution: must be an integer >= 1"),
        (["ok.toml", "--set", "jelly.0.size=1e999"], "jelly.0.size: must be a list of 3 finite numbers"),
        (["ok.toml", "--set", "name=\udcff"], "ok.toml: name: must be valid Unicode text"),
        (["deep.toml"], "deep.toml: line 11, column 114: arrays and inline tables nested deeper than 100 levels"),
        (["huge.toml"], "huge.toml: line 7, column 10: number too long"),
        (["inf.toml"], "inf.toml: jelly.0.size: must be a list of 3 finite numbers"),
        (["uni.toml"], 'uni.toml: jelly.0."\\u00b2": unknown key'),
        (["pipe.toml"], "pipe.toml: scene: is not a regular file"),
        (["adir.toml"], "adir.toml: scene: is a directory"),
        (["a\0b.toml"], "scene: a file name cannot contain a NUL character"),
        (["compare", "ok.toml", "--vary", "jelly.²=1,2"], 'command line: --vary: jelly."\\u00b2": expected an index'),
        (["compare", "ok.toml", "--vary", f"jelly.0.resolution={DEEP_RES},3"], "jelly.0.resolution: arrays and inline"),
        (["compare", "ok.toml", "--vary", "jelly.0.resolution=0x" + "f" * 5000 + ",3"], "number too long"),
        (["compare", "deep.toml"], "deep.toml: line 11, column 114: arrays and inline tables nested deeper"),
    ],
    ids=lambda a: None if isinstance(a, list) else a[:40],
)
def test_cli_one_line(args, expect, tmp_path, capsys, monkeypatch):
    (tmp_path / "deep.toml").write_text(rc.BASE.replace("resolution = [3, 3, 3]", "resolution = " + DEEP_RES))
    (tmp_path / "huge.toml").write_text(rc.BASE.replace("frames = 2", "frames = " + "9" * 5000))
    (tmp_path / "inf.toml").write_text(rc.BASE.replace("size = 0.5", "size = 1e999"))
    (tmp_path / "uni.toml").write_text(rc.BASE.replace("size = 0.5", 'size = 0.5\n"²" = 1'))
    os.mkfifo(tmp_path / "pipe.toml")
    (tmp_path / "adir.toml").mkdir()
    line = _cli(args, tmp_path, capsys, monkeypatch)
    assert expect in line, line[:500]


def test_deep_scene_real_process(tmp_path):
    """A real ``softsim run`` on a 10000-deep scene, and with an odd --set index: one line, exit 2, no traceback."""
    import subprocess  # noqa: PLC0415

    (tmp_path / "deep.toml").write_text(rc.BASE.replace("resolution = [3, 3, 3]", "resolution = " + DEEP_RES))
    (tmp_path / "ok.toml").write_text(rc.BASE)
    for argv, expect in (
        (["deep.toml"], "error: deep.toml: line 11, column 114: arrays and inline tables nested deeper than 100"),
        (["ok.toml", "--set", "jelly.٣.size=1"], 'error: command line: --set jelly."\\u0663": expected an index'),
    ):
        proc = subprocess.run(
            [sys.executable, "-m", "softsim_warp", "run", *argv, "--quiet"],
            cwd=tmp_path, capture_output=True, text=True, timeout=120,
        )
        assert proc.returncode == 2, proc.stderr[-2000:]
        assert "Traceback" not in proc.stderr and len(proc.stderr.splitlines()) == 1, proc.stderr[-2000:]
        assert proc.stderr.startswith(expect), proc.stderr[:300]
