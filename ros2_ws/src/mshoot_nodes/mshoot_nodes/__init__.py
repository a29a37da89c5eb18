"""mshoot_nodes: ROS 2 nodes (emulator, forecaster, MPC) over mshoot_core."""
