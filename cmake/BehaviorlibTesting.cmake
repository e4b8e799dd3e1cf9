# behaviorlib_add_test: every test of the project is declared through it, so
# that each has its label and its timeout (tests_declared_test checks it).
#
#   behaviorlib_add_test(NAME n LABEL unit|integration|e2e|bench [more labels]
#                        TIMEOUT s
#                        SOURCES ... [LIBS ...] [ARGS ...]     a GoogleTest program
#                        | COMMAND ...                          any other command
#                        [PROPERTIES name value ...]            more test properties
#                        [ENVIRONMENT NAME=VALUE ...])          its environment
#
# A program is built from SOURCES with GoogleTest and gmock, with the
# project's warnings as errors; unit and integration test code is built at
# -O1 (a third less compile time; the code under test keeps the build type's
# optimisation). Sanitized builds run 2-10x slower: their timeouts are 4x.
function(behaviorlib_add_test)
  cmake_parse_arguments(T "" "NAME;TIMEOUT" "LABEL;SOURCES;LIBS;ARGS;COMMAND;PROPERTIES;ENVIRONMENT"
    ${ARGN})
  if(NOT T_NAME OR NOT T_LABEL OR NOT T_TIMEOUT)
    message(FATAL_ERROR "behaviorlib_add_test(${T_NAME}): NAME, LABEL and TIMEOUT are required")
  endif()
  if(T_UNPARSED_ARGUMENTS)
    message(FATAL_ERROR "behaviorlib_add_test(${T_NAME}): unknown arguments ${T_UNPARSED_ARGUMENTS}")
  endif()
  if(T_SOURCES AND T_COMMAND OR NOT T_SOURCES AND NOT T_COMMAND)
    message(FATAL_ERROR "behaviorlib_add_test(${T_NAME}): give SOURCES or COMMAND")
  endif()
  if(BEHAVIORLIB_SANITIZE)
    math(EXPR T_TIMEOUT "${T_TIMEOUT} * 4")
  endif()
  if(T_SOURCES)
    add_executable(${T_NAME} ${T_SOURCES})
    target_link_libraries(${T_NAME} PRIVATE ${T_LIBS} GTest::gtest GTest::gmock GTest::gtest_main)
    behaviorlib_strict(${T_NAME})
    list(GET T_LABEL 0 _first)
    if(_first STREQUAL "unit" OR _first STREQUAL "integration")
      target_compile_options(${T_NAME} PRIVATE $<$<CONFIG:Release,RelWithDebInfo>:-O1>)
    endif()
    add_test(NAME ${T_NAME} COMMAND ${T_NAME} ${T_ARGS})
  else()
    add_test(NAME ${T_NAME} COMMAND ${T_COMMAND})
  endif()
  set_tests_properties(${T_NAME} PROPERTIES LABELS "${T_LABEL}" TIMEOUT ${T_TIMEOUT} ${T_PROPERTIES})
  # NAME=VALUE items, each one argument (a value may hold spaces); kept a list
  # here, where PROPERTIES would flatten it.
  if(T_ENVIRONMENT)
    set_tests_properties(${T_NAME} PROPERTIES ENVIRONMENT "${T_ENVIRONMENT}")
  endif()
endfunction()
