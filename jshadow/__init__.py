"""jshadow: differentiable soft shadows of deforming meshes with shadow fields and SH scaling.

Public entry points (DESIGN.md §4): :func:`load_config`, :func:`build_scene`, :func:`render`,
:func:`reference`; for many frames or receivers, :class:`Renderer` (stages compiled once, chunked
and sharded receivers) and :func:`render_frames`. Sub-packages: :mod:`jshadow.sh` (spherical
harmonics), :mod:`jshadow.geometry` (meshes, deformations), :mod:`jshadow.visibility` (ray casting,
base sphere visibility), :mod:`jshadow.scaling` (f_k, M_k), :mod:`jshadow.lights`,
:mod:`jshadow.sampling`, :mod:`jshadow.envlights` (a map's bright part as distant lights).
"""

from . import entities as entities
from . import geometry as geometry
from . import sh as sh
from .config import build_scene as build_scene
from .config import load_config as load_config
from .reference import reference as reference
from .runner import Renderer as Renderer
from .runner import render_frames as render_frames
from .scene import RenderResult as RenderResult
from .scene import render as render

__version__ = "0.1.0"
