"""Importing a folder of a user's meshes (``ScanDatabase.from_meshes``, what ``bodyspace import``
runs): OBJ, STL (corners mapped onto the folder's topology, or welded for the first file) and
NPY vertex files, in mm and Z up, against the bare reading of the same files (``load_mesh`` /
``np.load`` and stacking) in the same process. The ratio is what the checks cost: one topology,
one unit (mean edge lengths), the human size, the up axis and the label table."""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import best_time  # noqa: E402

from bodyspace.data.database import ScanDatabase  # noqa: E402
from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.mesh.io import load_mesh, save_mesh  # noqa: E402
from bodyspace.synth.foreign import to_frame  # noqa: E402
from bodyspace.synth.phenotype import PARAMETERS, PhenotypeModel  # noqa: E402

N = 40   # meshes of 13,380 vertices


def main() -> None:
    template = load_template()
    rng = np.random.default_rng(0)
    phenotypes = rng.uniform(0.2, 0.8, size=(N, len(PARAMETERS)))
    bodies = to_frame(PhenotypeModel(template).vertices(phenotypes), up="z", scale=1000.0)   # mm, Z up
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for suffix in ("obj", "stl", "npy"):
            folder = root / suffix
            folder.mkdir()
            rows = ["mesh,subject,stature_cm"]
            for i, body in enumerate(bodies):
                name = f"body_{i:03d}.{suffix}"
                if suffix == "npy":
                    np.save(folder / name, body)
                else:
                    save_mesh(folder / name, body, template.faces)
                rows.append(f"{name},s{i},{160 + i % 30}")
            (folder / "labels.csv").write_text("\n".join(rows) + "\n")
        save_mesh(root / "faces.obj", template.vertices, template.faces)
        print(f"import of {N} meshes of {template.n_vertices} vertices (mm, Z up), best of 3:")
        for suffix in ("obj", "stl", "npy"):
            folder = root / suffix
            faces = root / "faces.obj" if suffix == "npy" else None
            files = sorted(folder.glob(f"*.{suffix}"))

            def bare():
                read = [np.load(p) if suffix == "npy" else load_mesh(p)[0] for p in files]
                return np.stack(read).astype(np.float32)

            def imported():
                return ScanDatabase.from_meshes(folder, folder / "labels.csv", length_unit="mm", up="z", faces=faces)
            t_import, t_bare = best_time(imported), best_time(bare)
            print(f"  {suffix.upper()}: from_meshes {1000 * t_import / N:.1f} ms a mesh, bare reading "
                  f"{1000 * t_bare / N:.1f} ms a mesh: the checks cost x{t_import / t_bare:.2f}")


if __name__ == "__main__":
    main()
