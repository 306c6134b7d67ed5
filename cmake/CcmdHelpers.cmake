# Project-wide compile flags live on an interface target so every module gets the same ones.
add_library(ccmd_build_flags INTERFACE)
target_compile_options(ccmd_build_flags INTERFACE -Wall -Wextra)
if(CCMD_WERROR)
  target_compile_options(ccmd_build_flags INTERFACE -Werror)
endif()
if(CCMD_SANITIZE)
  target_compile_options(ccmd_build_flags INTERFACE
    -fsanitize=address,undefined -fno-omit-frame-pointer -fno-sanitize-recover=undefined)
  target_link_options(ccmd_build_flags INTERFACE -fsanitize=address,undefined)
endif()
if(CCMD_SANITIZE_THREAD)
  # ThreadSanitizer cannot share a process with AddressSanitizer: the two are separate builds.
  if(CCMD_SANITIZE)
    message(FATAL_ERROR "CCMD_SANITIZE_THREAD and CCMD_SANITIZE cannot be combined: ThreadSanitizer "
                        "and AddressSanitizer are separate builds (scripts/test.sh --tsan uses "
                        "build-tsan/, --sanitize build-asan/)")
  endif()
  # Once the code is instrumented, GCC's flow analysis warns of things it does not warn of
  # otherwise (maybe-uninitialized std::variant members, free-nonheap-object in vector
  # growth): false positives, shown but not stopping a -Werror build.
  target_compile_options(ccmd_build_flags INTERFACE -fsanitize=thread -fno-omit-frame-pointer
                         $<$<CXX_COMPILER_ID:GNU>:-Wno-error>)
  target_link_options(ccmd_build_flags INTERFACE -fsanitize=thread)
endif()

# ccmd_add_library(NAME SOURCES ... DEPS ... [PRIVATE_DEPS ...])
# One static library per libccmd module; includes are rooted at the repository
# ("libccmd/util/status.h") so a file's include says which module it uses.
function(ccmd_add_library name)
  cmake_parse_arguments(ARG "" "" "SOURCES;DEPS;PRIVATE_DEPS" ${ARGN})
  add_library(${name} STATIC ${ARG_SOURCES})
  target_include_directories(${name} PUBLIC ${PROJECT_SOURCE_DIR})
  target_link_libraries(${name} PUBLIC ${ARG_DEPS} ccmd_build_flags PRIVATE ${ARG_PRIVATE_DEPS})
endfunction()

# ccmd_add_executable(NAME SOURCES ... DEPS ...)
# The target is NAME_app (library targets own the module names); the program is bin/NAME.
function(ccmd_add_executable name)
  cmake_parse_arguments(ARG "" "" "SOURCES;DEPS" ${ARGN})
  add_executable(${name}_app ${ARG_SOURCES})
  target_include_directories(${name}_app PRIVATE ${PROJECT_SOURCE_DIR})
  target_link_libraries(${name}_app PRIVATE ${ARG_DEPS} ccmd_build_flags)
  set_target_properties(${name}_app PROPERTIES OUTPUT_NAME ${name}
                        RUNTIME_OUTPUT_DIRECTORY ${PROJECT_BINARY_DIR}/bin)
endfunction()

# ccmd_add_test(NAME SOURCES ... DEPS ... [LABELS ...] [TIMEOUT seconds] [CONCURRENT pattern ...])
# A GoogleTest binary registered test by test with ctest. CONCURRENT names, as GoogleTest
# filter patterns ("StageTest.*"), the tests that run several threads or processes: they get
# the label "concurrent" as well, which the ThreadSanitizer run selects (scripts/test.sh --tsan).
function(ccmd_add_test name)
  cmake_parse_arguments(ARG "" "TIMEOUT" "SOURCES;DEPS;LABELS;CONCURRENT" ${ARGN})
  if(NOT ARG_TIMEOUT)
    set(ARG_TIMEOUT 300)
  endif()
  add_executable(${name} ${ARG_SOURCES})
  target_link_libraries(${name} PRIVATE ${ARG_DEPS} ccmd_test_support GTest::gtest GTest::gtest_main
                        ccmd_build_flags)
  set_target_properties(${name} PROPERTIES RUNTIME_OUTPUT_DIRECTORY ${PROJECT_BINARY_DIR}/tests)
  set(discover_args DISCOVERY_MODE PRE_TEST DISCOVERY_TIMEOUT 60
      PROPERTIES TIMEOUT ${ARG_TIMEOUT} ENVIRONMENT "CCMD_BIN_DIR=${PROJECT_BINARY_DIR}/bin")
  if(ARG_LABELS)
    list(APPEND discover_args LABELS "${ARG_LABELS}")
  endif()
  if(NOT ARG_CONCURRENT)
    gtest_discover_tests(${name} ${discover_args})
    return()
  endif()
  # Two discoveries split the binary's tests; a list property cannot pass through
  # gtest_discover_tests, so the concurrent ones get their labels from an include file that
  # ctest reads after the discovered tests (TEST_LIST names them).
  list(JOIN ARG_CONCURRENT ":" filter)
  gtest_discover_tests(${name} ${discover_args} TEST_FILTER "${filter}"
                       TEST_LIST ${name}_concurrent_tests)
  gtest_discover_tests(${name} ${discover_args} TEST_FILTER "-${filter}")
  set(labels_file "${CMAKE_CURRENT_BINARY_DIR}/${name}_concurrent_labels.cmake")
  file(WRITE "${labels_file}"
    "foreach(test IN LISTS ${name}_concurrent_tests)\n"
    "  set_tests_properties(\"\${test}\" PROPERTIES LABELS \"${ARG_LABELS};concurrent\")\n"
    "endforeach()\n")
  set_property(DIRECTORY APPEND PROPERTY TEST_INCLUDE_FILES "${labels_file}")
endfunction()

# ccmd_link_closure(TARGET OUT_VAR): every target TARGET links, directly or through others.
function(ccmd_link_closure target out_var)
  set(seen "")
  set(todo ${target})
  while(todo)
    list(POP_FRONT todo current)
    if(NOT TARGET ${current} OR current IN_LIST seen)
      continue()
    endif()
    list(APPEND seen ${current})
    get_target_property(type ${current} TYPE)
    set(links "")
    if(NOT type STREQUAL "INTERFACE_LIBRARY")
      get_target_property(direct ${current} LINK_LIBRARIES)
      if(direct)
        list(APPEND links ${direct})
      endif()
    endif()
    get_target_property(interface ${current} INTERFACE_LINK_LIBRARIES)
    if(interface)
      list(APPEND links ${interface})
    endif()
    foreach(link ${links})
      string(REGEX REPLACE "^\\$<LINK_ONLY:(.*)>$" "\\1" link "${link}")
      list(APPEND todo ${link})
    endforeach()
  endwhile()
  list(REMOVE_ITEM seen ${target})
  set(${out_var} ${seen} PARENT_SCOPE)
endfunction()

# ccmd_forbid_links(TARGET LIB ...): configuration fails if TARGET links any of LIB, directly
# or through other libraries. Keeps a program's dependencies what its layer promises.
function(ccmd_forbid_links target)
  ccmd_link_closure(${target} closure)
  foreach(forbidden ${ARGN})
    if(forbidden IN_LIST closure)
      message(FATAL_ERROR "${target} must not link ${forbidden} (it links: ${closure})")
    endif()
  endforeach()
endfunction()
