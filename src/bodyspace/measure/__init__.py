"""Body measurements on any body mesh: Rupprecht's loops, ISO 8559-1 girths and lengths, mass.

Definitions are data (``definitions``: a JSON set per template, checked on load), each method
is one function in the registry ``methods.METHODS`` (``register_method`` adds one), the
point/axis grammar they share is ``points``, the geometry is ``slicing`` (plane
cross-sections, tape-measure girths), ``composition`` turns volume into mass, BMI and body fat,
and ``evaluate`` runs a set on bodies (V, 3) or batches (N, V, 3). docs/measurements.md lists
the default set. ``parts`` labels every vertex with its body part, so a girth's tape goes
round one part (docs/measurements.md, "Body parts"); ``tolerances`` holds the ISO 20685-1
tolerances by which two values of a measurement count as equal.
"""

from bodyspace.errors import MeasurementError
from bodyspace.measure.composition import body_density, body_fat_percent, mass_from_volume
from bodyspace.measure.definitions import (
    MeasurementSet,
    load_landmarks,
    load_measurement_set,
    measurement_set_from_dict,
    with_landmarks,
    with_standing_body,
    with_vertex_parts,
)
from bodyspace.measure.evaluate import Measurement, check_compatible, evaluate, measure, to_json
from bodyspace.measure.methods import METHODS, Chunk, Method, register_method
from bodyspace.measure.parts import PARTS, parts_from_landmarks, parts_from_weights

__all__ = [
    # definitions: measurement sets and landmark files
    "MeasurementError", "MeasurementSet", "load_landmarks", "load_measurement_set",
    "measurement_set_from_dict", "with_landmarks", "with_standing_body", "with_vertex_parts",
    # parts: the body part of every vertex (part-aware girths)
    "PARTS", "parts_from_landmarks", "parts_from_weights",
    # methods: the registry
    "METHODS", "Chunk", "Method", "register_method",
    # evaluate: running a set on bodies
    "Measurement", "check_compatible", "evaluate", "measure", "to_json",
    # composition: volume to mass, BMI, body fat
    "body_density", "body_fat_percent", "mass_from_volume",
]
