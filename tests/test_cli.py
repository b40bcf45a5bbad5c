import inspect
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import typer.main
from typer.core import TyperGroup
from typer.testing import CliRunner

from bodyspace.cli import COMMANDS, app, load_command
from bodyspace.data.database import ScanDatabase

runner = CliRunner()


def test_assets_command_reports_verified(template):
    result = runner.invoke(app, ["assets"])
    assert result.exit_code == 0, result.output
    assert "verified" in result.output and "yes" in result.output


def test_assets_command_on_incomplete_folder(tmp_path):
    result = runner.invoke(app, ["assets", "--assets", str(tmp_path)])
    assert result.exit_code == 1
    assert "missing" in result.output


def test_population_command(template, tmp_path):
    out = tmp_path / "db"
    result = runner.invoke(app, ["population", "--subjects", "2", "--poses", "1", "--seed", "3", "--out", str(out)])
    assert result.exit_code == 0, result.output
    db = ScanDatabase.load(out)
    assert db.n_scans == 4 and set(db.subjects["sex"]) == {"female", "male"}
    again = runner.invoke(app, ["population", "--subjects", "2", "--poses", "1", "--out", str(out)])
    assert again.exit_code == 2 and "already exists" in again.output and "--force" in again.output
    assert "writing the database" not in again.output, "refused before doing the work"


def test_demo_command_writes_pictures_and_summary(template, tmp_path):
    out = tmp_path / "demo"
    result = runner.invoke(app, ["demo", "--out", str(out), "--subjects", "4", "--poses", "1"])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    for png in summary["pictures"]:
        data = (out / png).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    assert summary["database"]["scans"] == 8
    female = summary["population"]["female"]
    assert female["subjects"] == 2
    assert np.isfinite(female["bmi_kg_m2"]["mean"])
    mapping = summary["mapping"]
    assert set(mapping["within_1mm"]) == {"linear", "forest", "forest + refinement"}
    # Leave-one-subject-out, shape-only and pose+shape, RRE with both projections and vertex PCA.
    general = summary["generalization"]
    for study in ("shape_only", "pose_and_shape"):
        assert set(general[study]["error_mm"]) == {"rre code", "rre vertex", "vertex"}
        assert all(np.isfinite(general[study]["error_mm"][m]).all() for m in general[study]["error_mm"])
    assert "rre PCA, vertex fit" in (out / general["table"]).read_text()
    assert (out / mapping["files"]["tables"]).read_text().count("|") > 20


def test_measure_command_json_csv_png(phenotype_model, template, tmp_path):
    from bodyspace.mesh.io import save_mesh
    mesh = tmp_path / "body.obj"
    save_mesh(mesh, phenotype_model.vertices({"gender": 1.0})[0], template.faces)
    result = runner.invoke(app, ["measure", str(mesh), "--json", "--png", str(tmp_path / "m.png")])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["stature"]["unit"] == "cm" and 160 < data["stature"]["value"] < 190
    assert data["mass"]["unit"] == "kg" and data["volume"]["unit"] == "m^3"
    assert (tmp_path / "m.png").read_bytes()[:4] == b"\x89PNG"
    csv_out = runner.invoke(app, ["measure", str(mesh), "--csv"])
    assert csv_out.exit_code == 0 and csv_out.stdout.splitlines()[0] == "mesh,name,value,unit,note"


def test_measure_command_rejects_wrong_topology(tmp_path):
    import trimesh

    from bodyspace.mesh.io import save_mesh
    sphere = trimesh.creation.icosphere(2)
    path = tmp_path / "sphere.obj"
    save_mesh(path, sphere.vertices, sphere.faces)
    result = runner.invoke(app, ["measure", str(path)])
    assert result.exit_code == 2
    assert "vertices" in result.output


# ----------------------------------------------------------------------------- lazy command loading
def test_help_lists_every_command_of_the_table():
    result = runner.invoke(app, ["--help"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    panel = result.output.split("─ Commands ")[1].splitlines()[1:]
    listed = [ln.split()[1] for ln in panel if ln.startswith("│ ") and ln[2] != " "]
    assert listed == list(COMMANDS)
    assert typer.main.get_command(app).list_commands(None) == list(COMMANDS)


@pytest.mark.parametrize("name", list(COMMANDS))
def test_table_entry_is_the_command_its_module_defines(name):
    """The table cannot drift from the code: the module defines the attribute, it builds a command
    of that name, and the one-line help the listing shows is the command's own (the first
    paragraph of its docstring, as typer lists it)."""
    entry = COMMANDS[name]
    command = load_command(name, entry)
    assert command.name == name
    assert command.short_help is None and not command.hidden and not command.deprecated
    assert getattr(command, "rich_help_panel", None) is None
    assert inspect.cleandoc(command.help).split("\n\n")[0] == entry.help
    if isinstance(command, TyperGroup):
        assert command.list_commands(None), f"{name}: a group without commands"
    else:
        assert inspect.unwrap(command.callback).__module__ == entry.module, "the function lives in its module"


def test_help_imports_no_command_module():
    """`bodyspace --help` reads the table: no command module, no heavy library is imported."""
    code = ("import sys\nfrom bodyspace.cli import main\nsys.argv = ['bodyspace', '--help']\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\n"
            "heavy = ('bodyspace.cli.measure', 'bodyspace.model', 'bodyspace.mesh', 'scipy', 'matplotlib', "
            "'numba', 'trimesh', 'numpy')\n"
            "print('IMPORTED', sorted(m for m in sys.modules if m.startswith(heavy)))")
    src = str(Path(__file__).resolve().parents[1] / "src")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": src})
    assert r.returncode == 0, r.stderr
    assert "IMPORTED []" in r.stdout, r.stdout[-500:]


def test_population_pose_set_gives_every_subject_the_same_poses(template, tmp_path):
    out = tmp_path / "db"
    result = runner.invoke(app, ["population", "--subjects", "2", "--pose-set", "squat, arms_crossed", "--seed", "3",
                                 "--out", str(out)])
    assert result.exit_code == 0, result.output
    db = ScanDatabase.load(out)
    assert db.n_scans == 6
    for s in db.subjects["subject"]:
        assert list(db.scans["pose"][db.scans["subject"] == s]) == ["rest", "squat", "arms_crossed"]
    assert json.loads((out / "meta.json").read_text())["provenance"]["pose_set"] == ["squat", "arms_crossed"]
    # Posed scans differ from the subject's rest scan; the two subjects' squats differ.
    v = np.asarray(db.read(np.arange(6)))
    assert np.abs(v[1] - v[0]).max() > 0.05 and np.abs(v[4] - v[1]).max() > 0.005
    for args, words in ((["--pose-set", "squat,no_such_pose"], ["--pose-set", "no_such_pose", "lunge_left"]),
                        (["--pose-set", "squat,squat"], ["named twice"]),
                        (["--pose-set", "rest"], ["'rest'", "rest pose first"]),
                        (["--pose-set", "standard", "--poses", "3"], ["--poses 3", "8 poses", "no --poses"])):
        bad = runner.invoke(app, ["population", "--subjects", "1", *args, "--out", str(tmp_path / "bad")])
        assert bad.exit_code == 2 and all(w in bad.output for w in words), bad.output
        assert "Traceback" not in bad.output and not (tmp_path / "bad").exists()
