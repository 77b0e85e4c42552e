"""Node parameters, ROS-free: vpr_node's one table, its checks, parameter files and the configs
built from the values (`table`, `check`, `file`, `configs`); the fleet's rows (`fleet`) and
posegraph_node's table (`posegraph`, import it on its own: it needs GTSAM).

`from pair_vpr_ros import params` gives vpr_node's parameter API below; `ros/parameters.py`
declares these as ROS parameters and the replay reads the same table for its flags.
"""

from pair_vpr_ros.params.check import TYPE_NAMES, check_value, flag_help, flag_type
from pair_vpr_ros.params.configs import (
    check_change,
    defaults,
    detector_config,
    geometry_config,
    index_config,
)
from pair_vpr_ros.params.file import (
    INSTALLED_CONFIG,
    VPR_NODE_HEADER,
    load_yaml,
    params_file_problem,
    read_params_file,
    yaml_text,
)
from pair_vpr_ros.params.table import DETECTOR_PARAMS, PARAMS, RANDOM_TINY, SPECS, ParamSpec, Value

__all__ = [
    "DETECTOR_PARAMS",
    "INSTALLED_CONFIG",
    "PARAMS",
    "RANDOM_TINY",
    "SPECS",
    "TYPE_NAMES",
    "VPR_NODE_HEADER",
    "ParamSpec",
    "Value",
    "check_change",
    "check_value",
    "defaults",
    "detector_config",
    "flag_help",
    "flag_type",
    "geometry_config",
    "index_config",
    "load_yaml",
    "params_file_problem",
    "read_params_file",
    "yaml_text",
]
