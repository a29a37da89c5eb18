"""mshoot_core: MPC with multiple shooting for buildings (pure Python, no ROS)."""
