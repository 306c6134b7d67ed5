ccmd_add_executable(ccmd_replay SOURCES ccmd_replay.cc DEPS ccmd_replay_report ccmd_netsim ccmd_io ccmd_sources ccmd_app_common)
# It starts these two, found next to it.
add_dependencies(ccmd_replay_app ccmd_server_app ccmd_agent_app)
