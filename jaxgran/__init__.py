"""jaxgran: a differentiable, vectorised 2D DEM of breakable grains, written in JAX."""

from .integrate import check_time_step as check_time_step
from .integrate import critical_time_step as critical_time_step
from .integrate import servo_gain_for as servo_gain_for
from .integrate import stable_time_step as stable_time_step
from .partition import make_grid as make_grid
from .simulate import SimulationError as SimulationError
from .simulate import prepare as prepare
from .simulate import run_segment as run_segment
from .state import Params as Params
from .state import Particles as Particles
from .state import SimState as SimState
from .state import Walls as Walls
from .state import box_walls as box_walls
from .state import make_params as make_params
from .state import make_state as make_state
from .state import make_walls as make_walls
from .state import particles_from_polygons as particles_from_polygons
from .state import wall as wall

__version__ = "0.1.0"
