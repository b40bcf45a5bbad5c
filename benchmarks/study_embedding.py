"""Run the embedding study (issue 13: the default rig embedded into foreign bodies, joint errors per
group) and print its Markdown table, headed by the date and the code it ran on.

Run: python benchmarks/study_embedding.py [bodies] [--out FILE]
(2-5 s a body on two loaded cores; ``--out`` writes the table to FILE as well).
"""

from __future__ import annotations

import datetime
import platform
import sys
from pathlib import Path

from bodyspace.data.template import load_template
from bodyspace.studies.embedding import embedding_study, markdown
from bodyspace.synth.phenotype import PhenotypeModel

sys.path.insert(0, str(Path(__file__).resolve().parent))
from study_pose_spread import _code_version, split_out_option  # noqa: E402  (one helper for every study script)


def main(argv: list[str]) -> None:
    argv, out = split_out_option(argv)
    n = int(argv[0]) if argv else 24
    template = load_template()
    study = embedding_study(template, PhenotypeModel(template), n_bodies=n, rng=2026)
    head = (f"Embedding study, {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, "
            f"{platform.node() or 'this machine'}, code {_code_version()}")
    text = head + "\n\n" + markdown(study) + "\n"
    print(text)
    if out is not None:
        out.write_text(text, encoding="utf-8")


if __name__ == "__main__":
    main(sys.argv[1:])
