"""Add-on preferences: the Python packages path on sys.path and the pip install button."""
from __future__ import annotations

import base64
import hashlib
import sys
import zipfile
from pathlib import Path

import blender_util
import pytest

bpy = pytest.importorskip("bpy")


@pytest.fixture(scope="module")
def prefs_mod():
    blender_util.enable_addon()
    return sys.modules[f"{blender_util.ADDON_MODULE}.bt4d_addon.preferences"]


@pytest.fixture()
def prefs(prefs_mod):
    p = bpy.context.preferences.addons[blender_util.ADDON_MODULE].preferences
    yield p
    p.python_path = ""
    p.pip_args = ""


def make_wheel(folder: Path, name="bt4dfake", version="0.1", value=42) -> Path:
    """A minimal pure-Python wheel (installable offline with --no-index)."""
    folder.mkdir(parents=True, exist_ok=True)
    dist = f"{name}-{version}.dist-info"
    files = {
        f"{name}/__init__.py": f"VALUE = {value}\n",
        f"{dist}/METADATA": f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n",
        f"{dist}/WHEEL": "Wheel-Version: 1.0\nGenerator: bt4d-test\nRoot-Is-Purelib: true\nTag: py3-none-any\n",
    }
    record = []
    for path, text in files.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(text.encode()).digest()).rstrip(b"=").decode()
        record.append(f"{path},sha256={digest},{len(text.encode())}")
    record.append(f"{dist}/RECORD,,")
    files[f"{dist}/RECORD"] = "\n".join(record) + "\n"
    whl = folder / f"{name}-{version}-py3-none-any.whl"
    with zipfile.ZipFile(whl, "w") as zf:
        for path, text in files.items():
            zf.writestr(path, text)
    return whl


def test_pip_command_targets_the_given_folder(prefs_mod, tmp_path):
    cmd = prefs_mod.pip_install_command(str(tmp_path), extra_args="--index-url https://example.invalid/simple")
    assert cmd[:4] == [sys.executable, "-m", "pip", "install"]
    assert cmd[cmd.index("--target") + 1] == str(tmp_path)
    assert "torch==2.13.0" in cmd and "--index-url" in cmd
    assert any(r.startswith("torch==") for r in prefs_mod.REQUIREMENTS)


def test_install_pins_are_requirements_txt_pins(prefs_mod):
    """Issue 45, defect 5: the button installs what requirements.txt pins, numpy included."""
    pinned = {}
    for line in (Path(__file__).resolve().parents[1] / "requirements.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, _, version = line.partition("==")
            pinned[name.lower()] = version
    ours = {r.split("==")[0].lower(): r.split("==")[1] for r in prefs_mod.REQUIREMENTS}
    assert all("==" in r for r in prefs_mod.REQUIREMENTS)
    runtime = {k: v for k, v in pinned.items() if k not in prefs_mod.DEVELOPMENT_ONLY}
    assert ours == runtime
    assert ours["numpy"].startswith("1.")


def test_pip_output_is_read_while_it_runs_and_cancel_stops_it(prefs_mod):
    """A long pip run cannot block on a full pipe, shows its latest line, and can be cancelled."""
    import time
    chatty = [sys.executable, "-c", "import sys\nfor i in range(4000): print('line', i, 'x' * 60)\n"
              "print('done', flush=True)\nimport time; time.sleep(0.2)"]
    run = prefs_mod.PipRun(chatty)  # ~280 kB: far more than a pipe holds
    deadline = time.time() + 60
    while run.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    assert run.poll() == 0 and run.latest == "done"
    slow = prefs_mod.PipRun([sys.executable, "-c", "import time\nprint('started', flush=True)\ntime.sleep(60)"])
    while not run.latest and time.time() < deadline:
        time.sleep(0.05)
    t0 = time.time()
    while slow.latest != "started" and time.time() < deadline:
        time.sleep(0.05)
    slow.cancel()
    assert slow.cancelled and slow.poll() is not None and time.time() - t0 < 30


def test_cuda_advice_is_extra_index_url(prefs_mod, prefs):
    """Issue 45, defect 4: the pip command installs numba, OpenEXR, ... too, which a CUDA wheel index
    does not carry: the advice is --extra-index-url (the index is added), never --index-url alone."""
    tip = prefs.bl_rna.properties["pip_args"].description
    assert "--extra-index-url" in tip and "--index-url" not in tip.replace("--extra-index-url", "")
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    assert "--extra-index-url" in readme and "--index-url" not in readme.replace("--extra-index-url", "")


def test_manifest_declares_the_network_permission():
    text = (Path(__file__).resolve().parents[1] / "blender_manifest.toml").read_text()
    assert "network =" in text.split("[permissions]")[1]


def test_extension_user_folder_is_available(prefs_mod):
    p = prefs_mod.user_site_packages()
    assert p and Path(p).name == "site-packages" and "bullettime4d" in p


def test_python_path_is_appended_and_removed(prefs_mod, prefs, tmp_path):
    site = tmp_path / "site-packages"
    (site / "bt4d_probe_mod").mkdir(parents=True)
    (site / "bt4d_probe_mod" / "__init__.py").write_text("OK = True\n")
    prefs.python_path = str(site)  # the update callback syncs sys.path
    entry = str(site.resolve())
    assert entry in sys.path
    assert sys.path.index(entry) > sys.path.index(str(Path(bpy.__file__).parent.parent))  # appended
    import bt4d_probe_mod
    assert bt4d_probe_mod.OK
    sys.modules.pop("bt4d_probe_mod")
    prefs.python_path = str(tmp_path / "does_not_exist")
    assert entry not in sys.path
    assert str((tmp_path / "does_not_exist").resolve()) not in sys.path  # missing folders are skipped
    prefs.python_path = ""
    assert entry not in sys.path


def test_torch_location_found_without_importing(prefs_mod):
    loc = prefs_mod.torch_location()  # the test venv has torch
    assert loc and Path(loc).name == "torch"


def test_install_dependencies_operator_installs_offline(prefs_mod, prefs, tmp_path):
    wheels = tmp_path / "wheels"
    make_wheel(wheels)
    target = tmp_path / "target"
    res = bpy.ops.bt4d.install_dependencies(packages="bt4dfake", target=str(target),
                                            extra_args=f"--no-index --find-links {wheels}")
    assert res == {"FINISHED"}
    assert (target / "bt4dfake" / "__init__.py").read_text() == "VALUE = 42\n"
    assert prefs.last_install_log.startswith("Installed")
    prefs.python_path = str(target)
    import bt4dfake
    assert bt4dfake.VALUE == 42
    sys.modules.pop("bt4dfake")


def test_install_dependencies_failure_is_reported(prefs_mod, prefs, tmp_path):
    with pytest.raises(RuntimeError, match="pip failed"):
        bpy.ops.bt4d.install_dependencies(packages="bt4d-no-such-package", target=str(tmp_path / "t"),
                                          extra_args=f"--no-index --find-links {tmp_path}")
    assert prefs.last_install_log.startswith("pip failed")
