"""Physical building blocks that device models are composed from (one block per module).

Each block is an Equinox module with SI fields whose names carry their unit; blocks never
solve, fit or read files. Import them from here, not from the private modules.
"""

from greybox.blocks._camera import AbstractReadout as AbstractReadout
from greybox.blocks._camera import Camera as Camera
from greybox.blocks._camera import SensorReadout as SensorReadout
from greybox.blocks._contacts import FrictionContacts as FrictionContacts
from greybox.blocks._contacts import FrictionLaw as FrictionLaw
from greybox.blocks._contacts import PlayContacts as PlayContacts
from greybox.blocks._contacts import directional_friction_N as directional_friction_N
from greybox.blocks._contacts import implicit_friction_step as implicit_friction_step
from greybox.blocks._contacts import play_step_per_cycle_m as play_step_per_cycle_m
from greybox.blocks._contacts import smooth_clip as smooth_clip
from greybox.blocks._joule import JouleHeating as JouleHeating
from greybox.blocks._mechanics import ChevronExact as ChevronExact
from greybox.blocks._mechanics import ChevronLinear as ChevronLinear
from greybox.blocks._mechanics import QuasiStaticShuttle as QuasiStaticShuttle
from greybox.blocks._mechanics import ThermalElongation as ThermalElongation
from greybox.blocks._mechanics import chevron_blocked_force_N as chevron_blocked_force_N
from greybox.blocks._mechanics import chevron_stiffness_N_per_m as chevron_stiffness_N_per_m
from greybox.blocks._mechanics import okada_tokumaru_cte as okada_tokumaru_cte
from greybox.blocks._optics import OPTICAL_CONSTANTS as OPTICAL_CONSTANTS
from greybox.blocks._optics import material_absorptance as material_absorptance
from greybox.blocks._optics import slab_absorptance as slab_absorptance
from greybox.blocks._optics import surface_reflectance as surface_reflectance
from greybox.blocks._robot import BodyGeometry as BodyGeometry
from greybox.blocks._robot import Locomotion as Locomotion
from greybox.blocks._robot import TwoSidedThermal as TwoSidedThermal
from greybox.blocks._robot import absorbed_fractions as absorbed_fractions
from greybox.blocks._spot import GaussianSpot as GaussianSpot
from greybox.blocks._spot import Rectangle as Rectangle
from greybox.blocks._spot import RectangularFrame as RectangularFrame
from greybox.blocks._thermal import STEFAN_BOLTZMANN as STEFAN_BOLTZMANN
from greybox.blocks._thermal import AbstractThermal as AbstractThermal
from greybox.blocks._thermal import FirstOrderThermal as FirstOrderThermal
from greybox.blocks._thermal import ThermalChain as ThermalChain
from greybox.blocks._thermal import ThermalNetwork as ThermalNetwork
