# Helpers to compile .proto files into C++/gRPC sources and to embed a
# descriptor set with source info (comments) into a binary.

get_target_property(BEHAVIORLIB_GRPC_CPP_PLUGIN gRPC::grpc_cpp_plugin LOCATION)

# behaviorlib_generate_grpc(<out_var> ROOT <dir> GEN_DIR <dir> PROTOS <files relative to ROOT>)
# Sets <out_var> to the generated .pb.cc and .grpc.pb.cc files.
function(behaviorlib_generate_grpc out_var)
  cmake_parse_arguments(G "" "ROOT;GEN_DIR" "PROTOS" ${ARGN})
  file(MAKE_DIRECTORY ${G_GEN_DIR})
  set(_srcs)
  foreach(_proto ${G_PROTOS})
    string(REGEX REPLACE "\\.proto$" "" _base ${_proto})
    add_custom_command(
      OUTPUT ${G_GEN_DIR}/${_base}.pb.cc ${G_GEN_DIR}/${_base}.pb.h
             ${G_GEN_DIR}/${_base}.grpc.pb.cc ${G_GEN_DIR}/${_base}.grpc.pb.h
      COMMAND protobuf::protoc
        --proto_path=${G_ROOT}
        --cpp_out=${G_GEN_DIR}
        --grpc_out=${G_GEN_DIR}
        --plugin=protoc-gen-grpc=${BEHAVIORLIB_GRPC_CPP_PLUGIN}
        ${G_ROOT}/${_proto}
      DEPENDS ${G_ROOT}/${_proto} protobuf::protoc
      COMMENT "protoc ${_proto}"
      VERBATIM)
    list(APPEND _srcs ${G_GEN_DIR}/${_base}.pb.cc ${G_GEN_DIR}/${_base}.grpc.pb.cc)
  endforeach()
  set(${out_var} ${_srcs} PARENT_SCOPE)
endfunction()

# behaviorlib_embed_descriptor_set(<out_cc> ROOT <dir> NAME <stem> NAMESPACE <ns>
#                                  FUNCTION <fn> [HEADER <h>] PROTOS <files>)
# Generates <out_cc>, defining <ns>::<fn>() -> std::string_view with the
# serialized FileDescriptorSet (imports and comments included) of PROTOS.
function(behaviorlib_embed_descriptor_set out_cc)
  cmake_parse_arguments(E "" "ROOT;NAME;NAMESPACE;FUNCTION;HEADER" "PROTOS" ${ARGN})
  set(_abs)
  foreach(_proto ${E_PROTOS})
    list(APPEND _abs ${E_ROOT}/${_proto})
  endforeach()
  set(_desc ${CMAKE_CURRENT_BINARY_DIR}/${E_NAME}.pb)
  set(_cc ${CMAKE_CURRENT_BINARY_DIR}/${E_NAME}.cc)
  add_custom_command(
    OUTPUT ${_desc}
    COMMAND protobuf::protoc
      --proto_path=${E_ROOT}
      --include_imports --include_source_info
      --descriptor_set_out=${_desc}
      ${_abs}
    DEPENDS ${_abs} protobuf::protoc
    COMMENT "protoc descriptor set ${E_NAME}"
    VERBATIM)
  add_custom_command(
    OUTPUT ${_cc}
    COMMAND ${CMAKE_COMMAND} -DINPUT=${_desc} -DOUTPUT=${_cc}
      -DNAMESPACE=${E_NAMESPACE} -DFUNCTION=${E_FUNCTION} -DHEADER=${E_HEADER}
      -P ${PROJECT_SOURCE_DIR}/cmake/embed_file.cmake
    DEPENDS ${_desc} ${PROJECT_SOURCE_DIR}/cmake/embed_file.cmake
    COMMENT "embedding descriptor set ${E_NAME}"
    VERBATIM)
  set(${out_cc} ${_cc} PARENT_SCOPE)
endfunction()
