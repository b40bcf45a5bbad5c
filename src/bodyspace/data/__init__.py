"""Data layer: the CC0 assets, the template body, phenotypes, rigs, populations and scan databases."""
