"""PlantDescription.of: the fields the learner and the controller read of a PlantInfo."""
import math

from metampc_msgs.msg import PlantInfo
from metampc_plant.plant_description import PlantDescription


def test_of_reads_a_plant_info_message():
    info = PlantInfo(family='quadruple_tank', theta=[0.7, 0.6], dt=5.0, substeps=4,
                     u_min=[0.0, 0.0], u_max=[10.0, 9.0], output_names=['h1', 'h2'],
                     clock_mode='lockstep', state_bound=50.0)
    assert PlantDescription.of(info) == PlantDescription(
        family='quadruple_tank', dt=5.0, u_min=(0.0, 0.0), u_max=(10.0, 9.0), n_y=2,
        lockstep=True, theta=(0.7, 0.6), substeps=4, state_bound=50.0)


def test_a_real_plant_tells_no_theta_and_runs_in_real_time():
    info = PlantInfo(family='', dt=0.02, u_min=[-2.0], u_max=[2.0],
                     output_names=['angle', 'rate', 'current'], clock_mode='realtime',
                     state_bound=math.inf)
    plant = PlantDescription.of(info)
    assert (plant.theta, plant.substeps, plant.lockstep, plant.n_y) == ((), 0, False, 3)
    assert isinstance(plant.u_min, tuple) and isinstance(plant.theta, tuple)
