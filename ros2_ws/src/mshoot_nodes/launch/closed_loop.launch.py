"""
Launch the closed loop on a ROS 2 install: emulator, forecaster, MPC (and a bag).

    ros2 launch mshoot_nodes closed_loop.launch.py
    ros2 launch mshoot_nodes closed_loop.launch.py scenario:=ou44 \
        data:=/path/to/measurements.csv hours:=72 record:=true bag:=out/bag

Parameters come from the package's config/*.yaml, then the launch arguments.
With record:=true the run is recorded with `ros2 bag record -s mcap` (rosbag2);
recorder:=mshoot uses the package's own recorder node instead. The emulator
starts once the ROS graph shows the endpoints of the run (the MPC, the
forecaster and the recorder): the readiness check every bring-up shares
(mshoot_nodes.readiness.run_requirements). The emulator and the MPC are
lifecycle nodes that configure and activate themselves (autostart:=true);
`ros2 lifecycle set /mpc deactivate` hands the building back to its own control. The PyPI
wheels used for development have no launch package: there, use the
`bringup` (one process) or `bringup_processes` executables.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess, RegisterEventHandler, Shutdown
from launch.conditions import IfCondition
from launch.event_handlers import OnProcessExit
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node

from mshoot_nodes.readiness import RECORDERS, run_requirements

TOPICS = ['/clock', '/zone/state', '/zone/disturbances', '/forecast', '/mpc/setpoint',
          '/mpc/status']


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory('mshoot_nodes'), 'config')
    scenario = LaunchConfiguration('scenario')
    data = LaunchConfiguration('data')
    hours = LaunchConfiguration('hours')
    bag = LaunchConfiguration('bag')
    shared = {'scenario': scenario, 'data': data, 'hours': hours}
    record_rosbag2 = PythonExpression(["'", LaunchConfiguration('record'), "' == 'true' and '",
                                       LaunchConfiguration('recorder'), "' == 'rosbag2'"])
    record_mshoot = PythonExpression(["'", LaunchConfiguration('record'), "' == 'true' and '",
                                      LaunchConfiguration('recorder'), "' == 'mshoot'"])
    # The endpoints the emulator waits for, by recorder: a list (the parameter reads it as YAML).
    by_recorder = {recorder: run_requirements(recorder) for recorder in RECORDERS}
    ready = PythonExpression([repr(by_recorder), "['", LaunchConfiguration('recorder'), "' if '",
                              LaunchConfiguration('record'), "' == 'true' else 'none']"])
    emulator = Node(package='mshoot_nodes', executable='emulator', name='emulator',
                    output='screen',
                    parameters=[os.path.join(config, 'emulator.yaml'), shared,
                                {'exit_when_done': True, 'start_delay_s': 1.0,
                                 'ready_endpoints': ready}])
    return LaunchDescription([
        DeclareLaunchArgument('scenario', default_value='synthetic',
                              description='synthetic | ou44 | path to an OU44-format CSV'),
        DeclareLaunchArgument('data', default_value='',
                              description='OU44 measurements.csv for scenario ou44'),
        DeclareLaunchArgument('hours', default_value='72', description='control steps'),
        DeclareLaunchArgument('record', default_value='false', description='record a bag'),
        DeclareLaunchArgument('recorder', default_value='rosbag2',
                              description='rosbag2 (ros2 bag record) | mshoot (recorder node)'),
        DeclareLaunchArgument('bag', default_value='mshoot_bag', description='bag directory'),
        Node(package='mshoot_nodes', executable='forecaster', name='forecaster',
             output='screen', parameters=[os.path.join(config, 'forecaster.yaml'), shared]),
        Node(package='mshoot_nodes', executable='mpc', name='mpc', output='screen',
             parameters=[os.path.join(config, 'mpc.yaml')]),
        ExecuteProcess(cmd=['ros2', 'bag', 'record', '-s', 'mcap', '-o', bag] + TOPICS,
                       output='screen', condition=IfCondition(record_rosbag2)),
        Node(package='mshoot_nodes', executable='recorder', name='recorder', output='screen',
             parameters=[os.path.join(config, 'recorder.yaml'), {'bag_path': bag}],
             condition=IfCondition(record_mshoot)),
        emulator,
        # The emulator exits when its scenario is over: end the whole launch then.
        RegisterEventHandler(OnProcessExit(target_action=emulator,
                                           on_exit=[Shutdown(reason='scenario over')])),
    ])
