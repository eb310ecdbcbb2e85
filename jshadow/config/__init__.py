"""Scene configuration: TOML schema, validation, and ``build_scene`` (DESIGN.md §4).

``load_config(path)`` reads a TOML scene (and optional ``[fit]``) into frozen equinox Modules whose
attributes mirror the TOML; every problem raises :class:`ConfigError`, one line naming the file and
the key. ``build_scene(config)`` turns it into a :class:`jshadow.entities.Scene`, differentiably in
the config's numbers. ``get_param``/``set_param`` address those numbers by dotted paths
("occluder.0.deform.amount").
"""

from ._build import AUTO_CONTACT_TESTS as AUTO_CONTACT_TESTS
from ._build import AUTO_ENVIRONMENT_LIGHTS as AUTO_ENVIRONMENT_LIGHTS
from ._build import AUTO_ENVIRONMENT_LIGHTS_DEFORMING as AUTO_ENVIRONMENT_LIGHTS_DEFORMING
from ._build import AUTO_ENVIRONMENT_LIGHTS_STATIC as AUTO_ENVIRONMENT_LIGHTS_STATIC
from ._build import AUTO_LAMP_TESTS_PER_FACE as AUTO_LAMP_TESTS_PER_FACE
from ._build import AUTO_MAPS_GRID as AUTO_MAPS_GRID
from ._build import AUTO_PENUMBRA_PAIRS as AUTO_PENUMBRA_PAIRS
from ._build import AUTO_SELF_RAYS_PAIRS as AUTO_SELF_RAYS_PAIRS
from ._build import auto_light_path as auto_light_path
from ._build import build_scene as build_scene
from ._build import clear_file_cache as clear_file_cache
from ._build import lamp_tests_per_face as lamp_tests_per_face
from ._build import maps_resolution as maps_resolution
from ._build import own_ray_pairs as own_ray_pairs
from ._build import plane_receivers as plane_receivers
from ._build import rotate_latlong_y as rotate_latlong_y
from ._errors import ConfigError as ConfigError
from ._errors import did_you_mean as did_you_mean
from ._load import config_from_dict as config_from_dict
from ._load import load_config as load_config
from ._params import get_param as get_param
from ._params import param_paths as param_paths
from ._params import set_param as set_param
from ._schema import AnimationConfig as AnimationConfig
from ._schema import Config as Config
from ._schema import DeformConfig as DeformConfig
from ._schema import EnvironmentConfig as EnvironmentConfig
from ._schema import FitConfig as FitConfig
from ._schema import LightConfig as LightConfig
from ._schema import MethodConfig as MethodConfig
from ._schema import OccluderConfig as OccluderConfig
from ._schema import ReceiverConfig as ReceiverConfig
