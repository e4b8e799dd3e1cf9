# `cmake --install`: what a behavior system built outside this repository
# needs (examples/out_of_tree_behavior, docs/writing-a-behavior.md):
#   include/    the library's headers and the generated proto headers
#   lib/        the static libraries
#   bin/        protoc-gen-behaviorlib
#   share/behaviorlib/proto/   the .proto files (declarations and generated services)
#   lib/cmake/behaviorlib/     behaviorlibConfig.cmake, the targets
#                              (behaviorlib::behavior_system, ...) and
#                              behaviorlib_generate_behaviors()/_grpc()
include(GNUInstallDirs)
include(CMakePackageConfigHelpers)

set(_exported
  behaviorlib_options_proto:options_proto
  behaviorlib_proto_messages:proto_messages
  behaviorlib_proto:proto
  behaviorlib_proto_descriptors:proto_descriptors
  behaviorlib_core:core
  behaviorlib_reflection_proto:reflection_proto
  behaviorlib_reflection:reflection
  behaviorlib_reactor_order:reactor_order
  behaviorlib_flags:flags
  behaviorlib_status_details:status_details
  behaviorlib_errors:errors
  behaviorlib_input_guard:input_guard
  behaviorlib_transport:transport
  behaviorlib_server_runtime:server_runtime
  behaviorlib_channel_topic:channel_topic
  behaviorlib_channel_client:channel_client
  behaviorlib_behavior_system:behavior_system
  protoc_gen_behaviorlib:protoc_gen_behaviorlib
)
set(_targets)
foreach(_pair ${_exported})
  string(REPLACE ":" ";" _pair ${_pair})
  list(GET _pair 0 _target)
  list(GET _pair 1 _name)
  set_target_properties(${_target} PROPERTIES EXPORT_NAME ${_name})
  list(APPEND _targets ${_target})
endforeach()

install(TARGETS ${_targets} EXPORT behaviorlibTargets
  ARCHIVE DESTINATION ${CMAKE_INSTALL_LIBDIR}
  RUNTIME DESTINATION ${CMAKE_INSTALL_BINDIR}
  INCLUDES DESTINATION ${CMAKE_INSTALL_INCLUDEDIR})

foreach(_dir
    ${PROJECT_SOURCE_DIR}/proto/include
    ${PROJECT_SOURCE_DIR}/services/errors/include
    ${PROJECT_SOURCE_DIR}/services/behaviorlib/core/include
    ${PROJECT_SOURCE_DIR}/services/behaviorlib/server/include
    ${PROJECT_SOURCE_DIR}/services/server_kit/include
    ${PROJECT_SOURCE_DIR}/services/server_kit/reflection/include
    ${PROJECT_SOURCE_DIR}/services/channel/include)
  install(DIRECTORY ${_dir}/ DESTINATION ${CMAKE_INSTALL_INCLUDEDIR} FILES_MATCHING PATTERN "*.h")
endforeach()
foreach(_dir ${PROJECT_BINARY_DIR}/proto/gen ${PROJECT_BINARY_DIR}/services/server_kit/reflection/gen)
  install(DIRECTORY ${_dir}/ DESTINATION ${CMAKE_INSTALL_INCLUDEDIR} FILES_MATCHING PATTERN "*.h")
endforeach()
install(DIRECTORY ${PROJECT_SOURCE_DIR}/proto/behaviorlib
  DESTINATION ${CMAKE_INSTALL_DATADIR}/behaviorlib/proto FILES_MATCHING PATTERN "*.proto")
install(DIRECTORY ${PROJECT_BINARY_DIR}/proto/gen/behaviorlib
  DESTINATION ${CMAKE_INSTALL_DATADIR}/behaviorlib/proto FILES_MATCHING PATTERN "*.proto")

set(_cmake_dir ${CMAKE_INSTALL_LIBDIR}/cmake/behaviorlib)
install(EXPORT behaviorlibTargets NAMESPACE behaviorlib:: DESTINATION ${_cmake_dir})
configure_package_config_file(${PROJECT_SOURCE_DIR}/cmake/behaviorlibConfig.cmake.in
  ${PROJECT_BINARY_DIR}/behaviorlibConfig.cmake INSTALL_DESTINATION ${_cmake_dir}
  PATH_VARS CMAKE_INSTALL_DATADIR)
install(FILES ${PROJECT_BINARY_DIR}/behaviorlibConfig.cmake
  ${PROJECT_SOURCE_DIR}/cmake/BehaviorlibProto.cmake ${PROJECT_SOURCE_DIR}/cmake/embed_file.cmake
  DESTINATION ${_cmake_dir})
