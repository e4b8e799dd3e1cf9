# Sanitizer and fuzzing builds (see docs/sanitizers.md and decision 25).
#
#   -DBEHAVIORLIB_SANITIZE=address,undefined   ASan + UBSan over everything we compile
#   -DBEHAVIORLIB_SANITIZE=thread              TSan, plus the absl::Mutex annotations
#   -DBEHAVIORLIB_FUZZ=ON                      libFuzzer targets (clang): our code gets
#                                              coverage instrumentation (fuzzer-no-link)
#
# The flags apply to every target we compile, generated code included; Debian's
# libraries stay as Debian built them (uninstrumented).
set(BEHAVIORLIB_SANITIZE "" CACHE STRING
    "Sanitizers for everything compiled here: address,undefined or thread (empty: none)")
option(BEHAVIORLIB_FUZZ "Build the libFuzzer targets of tests/fuzz (clang only)" OFF)

set(BEHAVIORLIB_TSAN OFF)
if(BEHAVIORLIB_SANITIZE)
  string(REPLACE "," ";" _behaviorlib_sanitizers "${BEHAVIORLIB_SANITIZE}")
  foreach(_s IN LISTS _behaviorlib_sanitizers)
    if(NOT _s MATCHES "^(address|undefined|thread)$")
      message(FATAL_ERROR "BEHAVIORLIB_SANITIZE: '${_s}' is not one of address, undefined, thread")
    endif()
    if(_s STREQUAL "thread")
      set(BEHAVIORLIB_TSAN ON)
    endif()
  endforeach()
  if(BEHAVIORLIB_TSAN AND "address" IN_LIST _behaviorlib_sanitizers)
    message(FATAL_ERROR "BEHAVIORLIB_SANITIZE: thread and address cannot be combined")
  endif()
  # Every finding stops the process (a test fails), not only a report.
  add_compile_options(-fsanitize=${BEHAVIORLIB_SANITIZE} -fno-sanitize-recover=all
                      -fno-omit-frame-pointer)
  add_link_options(-fsanitize=${BEHAVIORLIB_SANITIZE})
  if(BEHAVIORLIB_TSAN)
    add_compile_options(
      -fsanitize-ignorelist=${PROJECT_SOURCE_DIR}/tests/sanitizers/tsan_ignorelist.txt)
  endif()
endif()

if(BEHAVIORLIB_FUZZ)
  if(NOT CMAKE_CXX_COMPILER_ID STREQUAL "Clang")
    message(FATAL_ERROR "BEHAVIORLIB_FUZZ needs clang (e.g. -DCMAKE_CXX_COMPILER=clang++-14)")
  endif()
  add_compile_options(-fsanitize=fuzzer-no-link)
endif()

# Called once every target exists: in a TSan build every program and test
# links the absl::Mutex annotations (tests/sanitizers/tsan_absl_annotations.cc), so
# that the locks of Debian's uninstrumented abseil are seen by TSan.
function(behaviorlib_attach_sanitizer_runtime)
  if(NOT BEHAVIORLIB_TSAN)
    return()
  endif()
  add_library(behaviorlib_tsan_absl_annotations OBJECT
              ${PROJECT_SOURCE_DIR}/tests/sanitizers/tsan_absl_annotations.cc)
  target_link_libraries(behaviorlib_tsan_absl_annotations PRIVATE absl::synchronization)
  behaviorlib_strict(behaviorlib_tsan_absl_annotations)
  set(_dirs ${PROJECT_SOURCE_DIR})
  while(_dirs)
    list(POP_FRONT _dirs _dir)
    get_property(_sub DIRECTORY ${_dir} PROPERTY SUBDIRECTORIES)
    list(APPEND _dirs ${_sub})
    get_property(_targets DIRECTORY ${_dir} PROPERTY BUILDSYSTEM_TARGETS)
    foreach(_t IN LISTS _targets)
      get_target_property(_type ${_t} TYPE)
      if(_type STREQUAL "EXECUTABLE")
        target_link_libraries(${_t} PRIVATE behaviorlib_tsan_absl_annotations ${CMAKE_DL_LIBS})
      endif()
    endforeach()
  endwhile()
endfunction()
