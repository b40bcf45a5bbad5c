"""One error hierarchy for the whole package.

Every message names the file or field, what was found and what was expected, so a user can
fix the input without reading our code.
"""


class BodyspaceError(Exception):
    """Base class of every error bodyspace raises on purpose."""


class AssetError(BodyspaceError):
    """The CC0 asset set is missing, incomplete, or does not verify."""


class MeshError(BodyspaceError):
    """A mesh has the wrong shape, topology or values."""


class UnposeError(MeshError):
    """A mesh of the template's topology cannot be brought back to the rest pose: after the best
    fit of the rig its rest body is still far from any of the template's (shuffled vertex order,
    or not a human body). Callers that can go on with the posed mesh catch this one only."""


class DatabaseError(BodyspaceError):
    """A scan database folder or a user's mesh folder is malformed."""


class ParameterError(BodyspaceError):
    """A phenotype or pose parameter is unknown or out of range."""


class UnitError(ParameterError):
    """A quantity has no unit, an unknown unit, or a unit of the wrong kind for its field."""


class TargetError(ParameterError):
    """A requested label value is outside what the model can reach, or was not met."""


class ModelError(BodyspaceError):
    """A BodyModel file is not one, has another format version, or misses or garbles a field."""


class MeasurementError(BodyspaceError):
    """A measurement set, a landmark file, or a measurement on a given mesh is invalid."""


class OutputError(BodyspaceError):
    """An output path exists, is not bodyspace's to replace, or cannot be written."""


class SemanticsFileError(BodyspaceError):
    """Stored semantic regressors (in a model file, or a legacy MODEL.semantics.npz) are damaged,
    incomplete, or were fitted on another model."""


class MotionError(BodyspaceError):
    """A motion file (BVH) is malformed, or a skeleton match or its map file cannot be made or read."""


class RigError(BodyspaceError):
    """A mesh cannot be rigged: several components, not a humanoid, far from closed, or a
    skeleton that does not fit inside it."""


class RegistrationError(BodyspaceError):
    """A scan cannot be registered: too few points, no body of the right size, or a fit that
    explains too little of it (two people, an object, a scan cut short)."""
