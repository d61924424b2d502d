# Small helpers so every module is declared the same way (COLMAP's colmap_add_library pattern).

set(PRISM_WARNING_FLAGS -Wall -Wextra)
if(PRISM_WERROR)
  list(APPEND PRISM_WARNING_FLAGS -Werror)
endif()

# prism_add_library(NAME name SRCS ... [PUBLIC_LINK ...] [PRIVATE_LINK ...])
function(prism_add_library)
  cmake_parse_arguments(ARG "" "NAME" "SRCS;PUBLIC_LINK;PRIVATE_LINK" ${ARGN})
  add_library(${ARG_NAME} STATIC ${ARG_SRCS})
  target_include_directories(${ARG_NAME} PUBLIC ${PROJECT_SOURCE_DIR})
  target_compile_options(${ARG_NAME} PRIVATE ${PRISM_WARNING_FLAGS})
  set_target_properties(${ARG_NAME} PROPERTIES POSITION_INDEPENDENT_CODE ON)
  target_link_libraries(${ARG_NAME} PUBLIC ${ARG_PUBLIC_LINK} PRIVATE ${ARG_PRIVATE_LINK})
endfunction()

# prism_add_executable(NAME name SRCS ... [LINK ...])
function(prism_add_executable)
  cmake_parse_arguments(ARG "" "NAME" "SRCS;LINK" ${ARGN})
  add_executable(${ARG_NAME} ${ARG_SRCS})
  target_compile_options(${ARG_NAME} PRIVATE ${PRISM_WARNING_FLAGS})
  target_link_libraries(${ARG_NAME} PRIVATE ${ARG_LINK})
  install(TARGETS ${ARG_NAME} RUNTIME DESTINATION bin)
endfunction()

# prism_add_test(NAME name SRCS ... [LINK ...] [LABELS unit|integration|slow ...] [SLOW_FILTER pattern])
# Each GoogleTest case becomes its own CTest test carrying the labels; the cases matching SLOW_FILTER
# (a --gtest_filter pattern, e.g. "*orbit*:*supersampled2*") carry the label slow instead.
function(prism_add_test)
  if(NOT PRISM_BUILD_TESTS)
    return()
  endif()
  cmake_parse_arguments(ARG "" "NAME;TIMEOUT;SLOW_FILTER" "SRCS;LINK;LABELS" ${ARGN})
  if(NOT ARG_LABELS)
    set(ARG_LABELS unit)
  endif()
  # TIMEOUT (seconds) overrides ctest's --timeout for this executable's tests.
  set(timeout_property "")
  if(ARG_TIMEOUT)
    set(timeout_property TIMEOUT ${ARG_TIMEOUT})
  endif()
  add_executable(${ARG_NAME} ${ARG_SRCS})
  target_include_directories(${ARG_NAME} PRIVATE ${PROJECT_SOURCE_DIR})
  target_compile_options(${ARG_NAME} PRIVATE ${PRISM_WARNING_FLAGS})
  target_link_libraries(${ARG_NAME} PRIVATE ${ARG_LINK} GTest::gtest GTest::gtest_main)
  target_compile_definitions(${ARG_NAME} PRIVATE
    PRISM_SHARED_DATA_DIR="${PRISM_SHARED_DATA_DIR}"
    PRISM_BINARY_DIR="${CMAKE_BINARY_DIR}")
  if(ARG_SLOW_FILTER)
    gtest_discover_tests(${ARG_NAME}
      TEST_FILTER "-${ARG_SLOW_FILTER}"
      PROPERTIES LABELS "${ARG_LABELS}" ${timeout_property}
      DISCOVERY_TIMEOUT 60)
    gtest_discover_tests(${ARG_NAME}
      TEST_FILTER "${ARG_SLOW_FILTER}"
      PROPERTIES LABELS slow ${timeout_property}
      DISCOVERY_TIMEOUT 60)
  else()
    gtest_discover_tests(${ARG_NAME}
      PROPERTIES LABELS "${ARG_LABELS}" ${timeout_property}
      DISCOVERY_TIMEOUT 60)
  endif()
endfunction()

# prism_add_benchmark(NAME name SRCS ... [LINK ...])
function(prism_add_benchmark)
  if(NOT PRISM_BUILD_BENCHMARKS)
    return()
  endif()
  cmake_parse_arguments(ARG "" "NAME" "SRCS;LINK" ${ARGN})
  add_executable(${ARG_NAME} ${ARG_SRCS})
  target_compile_options(${ARG_NAME} PRIVATE ${PRISM_WARNING_FLAGS})
  target_link_libraries(${ARG_NAME} PRIVATE ${ARG_LINK} benchmark::benchmark)
endfunction()
