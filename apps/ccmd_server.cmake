ccmd_add_executable(ccmd_server SOURCES ccmd_server.cc DEPS ccmd_server_runtime ccmd_net ccmd_app_common)
if(TARGET ccmd_default_vocabulary)
  add_dependencies(ccmd_server_app ccmd_default_vocabulary)
endif()
