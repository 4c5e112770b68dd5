"""``mujoco.mjx`` imported without its mesh libraries (jaxrobo.physics.mjx_import): none of them loaded by the
import, a mesh model's convex hull the same as with them imported up front, version-guarded."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from jaxrobo.physics import mjx_import

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _guard_refuses() -> bool:
    """Whether the fresh processes these tests start would import MJX as it is (the installed version is not the
    one it was written for), whatever this process (another test module, collected first) has imported already."""
    reason = mjx_import.unavailable()
    return reason is not None and reason != mjx_import.IMPORTED_ALREADY


GUARDED = pytest.mark.skipif(_guard_refuses(), reason="the installed mujoco-mjx is not the one it was written for "
                             "(jaxrobo.physics.mjx_import.unavailable)")

#: A tetrahedron mesh geom: MJX builds its convex hull with trimesh and scipy.spatial.
HULL = """
import json, sys
import mujoco
{import_line}
loaded = sorted(n for n in ("trimesh", "scipy.spatial") if n in sys.modules)
xml = '''<mujoco><asset><mesh name="tet" vertex="0 0 0  1 0 0  0 1 0  0 0 1  0.2 0.2 0.2"/></asset>
<worldbody><body><freejoint/><geom type="mesh" mesh="tet"/></body>
<geom type="plane" size="1 1 .1"/></worldbody></mujoco>'''
m = mjx.put_model(mujoco.MjModel.from_xml_string(xml))
hull = m.mesh_convex[0]
print(json.dumps({{"loaded_by_import": loaded, "vert": hull.vert.tolist(), "face": hull.face.tolist(),
                  "edge": hull.edge.tolist(), "loaded_after": "trimesh" in sys.modules}}))
"""


def _run(import_line: str) -> dict:
    env = {**os.environ, "PYTHONPATH": ROOT, "JAX_PLATFORMS": "cpu"}
    proc = subprocess.run([sys.executable, "-c", HULL.format(import_line=import_line)], env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


@GUARDED
def test_mjx_imports_without_mesh_libraries_and_builds_the_same_hulls():
    deferred = _run("from jaxrobo.physics.mjx_import import import_mjx; mjx = import_mjx()")
    stock = _run("import trimesh, scipy.spatial; import mujoco.mjx as mjx")
    assert deferred["loaded_by_import"] == []  # neither is imported until a mesh hull is built
    assert stock["loaded_by_import"] == ["scipy.spatial", "trimesh"]
    assert deferred["loaded_after"]
    for key in ("vert", "face", "edge"):
        assert deferred[key] == stock[key], key
    assert len(deferred["vert"]) == 4  # the hull: the inner vertex is not on it


def test_outside_the_versions_it_was_written_for_mjx_is_imported_as_it_is(monkeypatch):
    """Under a version it was not written for, the guard says why and ``import_mjx`` is the stock import: the mesh
    libraries load with it, and the hull is the stock one (checked in a fresh process)."""
    monkeypatch.setattr(mjx_import, "installed_version", lambda: "3.99.0")
    assert "outside the versions it was written for" in mjx_import.unavailable()
    patched = _run("from jaxrobo.physics import mjx_import; mjx_import.installed_version = lambda: '3.99.0'; "
                   "mjx = mjx_import.import_mjx()")
    assert patched["loaded_by_import"] == ["scipy.spatial", "trimesh"]
    stock = _run("import mujoco.mjx as mjx")
    assert all(patched[key] == stock[key] for key in ("vert", "face", "edge"))


def test_the_lines_about_warp_not_installed_are_not_said_and_other_output_is():
    """MJX prints two "Failed to import" lines on import where its optional Warp backend is not installed;
    jaxrobo's import drops exactly those (also where Brax imports MJX: jaxrobo's Brax face imports it first),
    and any other output of the import is written as it came."""
    env = {**os.environ, "PYTHONPATH": ROOT, "JAX_PLATFORMS": "cpu"}
    for module in ("jaxrobo.physics.mjx_import as m; m.import_mjx()", "jaxrobo.interop.brax_env"):
        proc = subprocess.run([sys.executable, "-c", f"import {module}"], env=env, capture_output=True, text=True,
                              timeout=300)
        assert proc.returncode == 0, proc.stderr
        assert "Failed to import" not in proc.stdout + proc.stderr, module
    import io
    from contextlib import redirect_stdout

    out = io.StringIO()
    with redirect_stdout(out):
        with mjx_import._quiet_about_warp():
            print("Failed to import warp: No module named 'warp'")
            print("Failed to import mujoco_warp: No module named 'warp'")
            print("Failed to import warp: CUDA driver too old")  # an installed Warp that fails: said
            print("something else")
    assert out.getvalue() == "Failed to import warp: CUDA driver too old\nsomething else\n"


@GUARDED
def test_an_installed_warp_is_kept_out_of_the_import_and_imports_as_usual_afterwards(tmp_path):
    """A ``warp`` package on the path (standing in for warp-lang, which marks its import): jaxrobo's MJX import does
    not import it, MJX reads its Warp backend as not installed and says nothing about it, and an ``import warp``
    afterwards imports it."""
    (tmp_path / "warp").mkdir()
    (tmp_path / "warp" / "__init__.py").write_text("import sys\nsys.stderr.write('WARP IMPORTED\\n')\n")
    code = ("import sys; from jaxrobo.physics.mjx_import import import_mjx; mjx = import_mjx(); "
            "print('during', 'warp' in sys.modules, mjx.warp.WARP_INSTALLED); "
            "import warp; print('after', warp.__file__)")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), ROOT]), "JAX_PLATFORMS": "cpu"}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.count("WARP IMPORTED") == 1  # once: by the program's own import, not by MJX's
    lines = proc.stdout.splitlines()
    assert lines == ["during False False", f"after {tmp_path / 'warp' / '__init__.py'}"]
    assert "Failed to import" not in proc.stdout
