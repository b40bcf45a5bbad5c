"""Body measurements on any body mesh: Rupprecht's loops, ISO 8559-1 girths and lengths, mass.

Definitions are data (``definitions``: a JSON set per template), the geometry is
``slicing`` (plane cross-sections, tape-measure girths) and ``evaluate`` runs a set on bodies
(V, 3) or batches (N, V, 3). docs/measurements.md lists the default set.
"""

from bodyspace.measure.definitions import (
                                           MeasurementError,
                                           MeasurementSet,
                                           load_landmarks,
                                           load_measurement_set,
                                           measurement_set_from_dict,
                                           with_landmarks,
)
from bodyspace.measure.evaluate import Measurement, evaluate, measure, to_json

__all__ = ["Measurement", "MeasurementError", "MeasurementSet", "evaluate", "load_landmarks",
           "load_measurement_set", "measure", "measurement_set_from_dict", "to_json", "with_landmarks"]
