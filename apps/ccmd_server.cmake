ccmd_add_executable(ccmd_server SOURCES ccmd_server.cc DEPS ccmd_net ccmd_app_common)
