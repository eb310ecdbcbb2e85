"""jaxtyping aliases used in every signature of jshadow.

Shapes use jaxtyping's notation: ``...`` are leading batch axes, ``n2`` is the number of SH
coefficients (n bands -> n² coefficients), ``V``/``F`` vertex and face counts.
"""

from jaxtyping import Array, ArrayLike, Bool, Float, Int

Scalar = Float[Array, ""]
ScalarLike = float | Float[ArrayLike, ""]
Vec3 = Float[Array, "... 3"]
Dirs = Float[Array, "... 3"]  # unit vectors
Points = Float[Array, "... 3"]
Rot3 = Float[Array, "... 3 3"]
SHCoeffs = Float[Array, "... n2"]
SHCoeffsRGB = Float[Array, "... n2 3"]
SHMatrix = Float[Array, "... n2 n2"]
Vertices = Float[Array, "V 3"]
Faces = Int[Array, "F 3"]
Mask = Bool[Array, "..."]

__all__ = [
    "Array",
    "ArrayLike",
    "Bool",
    "Dirs",
    "Faces",
    "Float",
    "Int",
    "Mask",
    "Points",
    "Rot3",
    "SHCoeffs",
    "SHCoeffsRGB",
    "SHMatrix",
    "Scalar",
    "ScalarLike",
    "Vec3",
    "Vertices",
]
