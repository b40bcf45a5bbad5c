"""Synthesis: MakeHuman phenotypes, the pose library and the synthetic scan population."""
