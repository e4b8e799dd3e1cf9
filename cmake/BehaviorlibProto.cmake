# Helpers to compile .proto files into C++/gRPC sources and to embed a
# descriptor set with source info (comments) into a binary.

get_target_property(BEHAVIORLIB_GRPC_CPP_PLUGIN gRPC::grpc_cpp_plugin LOCATION)
# Where this file is (the source tree, or an installed package's cmake dir).
set(_BEHAVIORLIB_CMAKE_DIR ${CMAKE_CURRENT_LIST_DIR})

# _behaviorlib_protoc(<out_var> ROOT <dir> GEN_DIR <dir> [INCLUDES <dirs>] PROTOS <files>
#                     OUTPUTS <suffixes> RESULTS <suffixes> ARGS <protoc args>
#                     [DEPENDS <targets>] COMMENT <text>)
# One protoc run per file X.proto (relative to ROOT) making GEN_DIR/X<suffix>
# for each of OUTPUTS; sets <out_var> to those of RESULTS.
function(_behaviorlib_protoc out_var)
  cmake_parse_arguments(P "" "ROOT;GEN_DIR;COMMENT"
    "PROTOS;INCLUDES;OUTPUTS;RESULTS;ARGS;DEPENDS" ${ARGN})
  file(MAKE_DIRECTORY ${P_GEN_DIR})
  set(_include_args)
  foreach(_dir ${P_INCLUDES})
    list(APPEND _include_args --proto_path=${_dir})
  endforeach()
  set(_results)
  foreach(_proto ${P_PROTOS})
    string(REGEX REPLACE "\\.proto$" "" _base ${_proto})
    set(_outputs)
    foreach(_suffix ${P_OUTPUTS})
      list(APPEND _outputs ${P_GEN_DIR}/${_base}${_suffix})
    endforeach()
    foreach(_suffix ${P_RESULTS})
      list(APPEND _results ${P_GEN_DIR}/${_base}${_suffix})
    endforeach()
    add_custom_command(
      OUTPUT ${_outputs}
      COMMAND protobuf::protoc --proto_path=${P_ROOT} ${_include_args} ${P_ARGS}
        ${P_ROOT}/${_proto}
      DEPENDS ${P_ROOT}/${_proto} protobuf::protoc ${P_DEPENDS}
      COMMENT "${P_COMMENT} ${_proto}"
      VERBATIM)
  endforeach()
  set(${out_var} ${_results} PARENT_SCOPE)
endfunction()

# behaviorlib_generate_grpc(<out_var> ROOT <dir> GEN_DIR <dir> [INCLUDES <dirs>]
#                           PROTOS <files relative to ROOT>)
# Sets <out_var> to the generated .pb.cc and .grpc.pb.cc files. INCLUDES are
# further import roots.
function(behaviorlib_generate_grpc out_var)
  cmake_parse_arguments(G "" "ROOT;GEN_DIR" "PROTOS;INCLUDES" ${ARGN})
  _behaviorlib_protoc(_srcs ROOT ${G_ROOT} GEN_DIR ${G_GEN_DIR} INCLUDES ${G_INCLUDES}
    PROTOS ${G_PROTOS}
    OUTPUTS .pb.cc .pb.h .grpc.pb.cc .grpc.pb.h RESULTS .pb.cc .grpc.pb.cc
    ARGS --cpp_out=${G_GEN_DIR} --grpc_out=${G_GEN_DIR}
      --plugin=protoc-gen-grpc=${BEHAVIORLIB_GRPC_CPP_PLUGIN}
    COMMENT "protoc")
  set(${out_var} ${_srcs} PARENT_SCOPE)
endfunction()

# behaviorlib_generate_cpp(<out_var> ROOT <dir> GEN_DIR <dir> [INCLUDES <dirs>]
#                          PROTOS <files relative to ROOT>)
# Messages only (no services): sets <out_var> to the generated .pb.cc files.
function(behaviorlib_generate_cpp out_var)
  cmake_parse_arguments(G "" "ROOT;GEN_DIR" "PROTOS;INCLUDES" ${ARGN})
  _behaviorlib_protoc(_srcs ROOT ${G_ROOT} GEN_DIR ${G_GEN_DIR} INCLUDES ${G_INCLUDES}
    PROTOS ${G_PROTOS} OUTPUTS .pb.cc .pb.h RESULTS .pb.cc ARGS --cpp_out=${G_GEN_DIR}
    COMMENT "protoc")
  set(${out_var} ${_srcs} PARENT_SCOPE)
endfunction()

# behaviorlib_generate_behaviors(<out_var> ROOT <dir> GEN_DIR <dir> [INCLUDES <dirs>]
#                                PROTOS <files>)
# Runs protoc-gen-behaviorlib (decision 21) on each declaration file X.proto
# (relative to ROOT): writes GEN_DIR/X_services.proto and GEN_DIR/X.behaviors.h,
# and sets <out_var> to the generated .proto files, relative to GEN_DIR.
function(behaviorlib_generate_behaviors out_var)
  cmake_parse_arguments(B "" "ROOT;GEN_DIR" "PROTOS;INCLUDES" ${ARGN})
  _behaviorlib_protoc(_generated ROOT ${B_ROOT} GEN_DIR ${B_GEN_DIR} INCLUDES ${B_INCLUDES}
    PROTOS ${B_PROTOS}
    OUTPUTS _services.proto .behaviors.h RESULTS _services.proto
    ARGS --plugin=protoc-gen-behaviorlib=$<TARGET_FILE:behaviorlib::protoc_gen_behaviorlib>
      --behaviorlib_out=${B_GEN_DIR}
    DEPENDS behaviorlib::protoc_gen_behaviorlib
    COMMENT "protoc-gen-behaviorlib")
  set(_relative)
  foreach(_file ${_generated})
    file(RELATIVE_PATH _rel ${B_GEN_DIR} ${_file})
    list(APPEND _relative ${_rel})
  endforeach()
  set(${out_var} ${_relative} PARENT_SCOPE)
endfunction()

# behaviorlib_embed_descriptor_set(<out_cc> ROOT <dir> NAME <stem> NAMESPACE <ns>
#                                  FUNCTION <fn> [HEADER <h>] PROTOS <files>
#                                  [GEN_ROOT <dir> GEN_PROTOS <files>]
#                                  [IMPORT_ROOT <dir> IMPORT_PROTOS <files>])
# Generates <out_cc>, defining <ns>::<fn>() -> std::string_view with the
# serialized FileDescriptorSet (imports and comments included) of PROTOS
# (relative to ROOT), GEN_PROTOS (relative to GEN_ROOT) and IMPORT_PROTOS
# (relative to IMPORT_ROOT: third-party files, e.g. google/rpc/*.proto).
function(behaviorlib_embed_descriptor_set out_cc)
  cmake_parse_arguments(E "" "ROOT;NAME;NAMESPACE;FUNCTION;HEADER;GEN_ROOT;IMPORT_ROOT"
    "PROTOS;GEN_PROTOS;IMPORT_PROTOS" ${ARGN})
  set(_abs)
  foreach(_proto ${E_PROTOS})
    list(APPEND _abs ${E_ROOT}/${_proto})
  endforeach()
  set(_roots --proto_path=${E_ROOT})
  if(E_GEN_ROOT)
    list(APPEND _roots --proto_path=${E_GEN_ROOT})
    foreach(_proto ${E_GEN_PROTOS})
      list(APPEND _abs ${E_GEN_ROOT}/${_proto})
    endforeach()
  endif()
  if(E_IMPORT_ROOT)
    list(APPEND _roots --proto_path=${E_IMPORT_ROOT})
    foreach(_proto ${E_IMPORT_PROTOS})
      list(APPEND _abs ${E_IMPORT_ROOT}/${_proto})
    endforeach()
  endif()
  set(_desc ${CMAKE_CURRENT_BINARY_DIR}/${E_NAME}.pb)
  set(_cc ${CMAKE_CURRENT_BINARY_DIR}/${E_NAME}.cc)
  add_custom_command(
    OUTPUT ${_desc}
    COMMAND protobuf::protoc
      ${_roots}
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
      -P ${_BEHAVIORLIB_CMAKE_DIR}/embed_file.cmake
    DEPENDS ${_desc} ${_BEHAVIORLIB_CMAKE_DIR}/embed_file.cmake
    COMMENT "embedding descriptor set ${E_NAME}"
    VERBATIM)
  set(${out_cc} ${_cc} PARENT_SCOPE)
endfunction()
