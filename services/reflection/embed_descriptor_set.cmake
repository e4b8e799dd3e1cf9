# Writes INPUT as a C++ byte array into OUTPUT, exposing
#   behaviorlib::reflection_internal::grpcDescriptorSet() -> std::string_view
file(READ ${INPUT} _hex HEX)
string(LENGTH "${_hex}" _len)
math(EXPR _bytes "${_len} / 2")
string(REGEX REPLACE "([0-9a-f][0-9a-f])" "0x\\1," _arr "${_hex}")
string(REGEX REPLACE "(0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,)" "\\1\n" _arr "${_arr}")
file(WRITE ${OUTPUT}
"// Generated from the gRPC health/reflection descriptor set; do not edit.\n"
"#include <string_view>\n"
"namespace {\n"
"const unsigned char kData[${_bytes}] = {\n${_arr}\n};\n"
"}  // namespace\n"
"namespace behaviorlib::reflection_internal {\n"
"std::string_view grpcDescriptorSet();\n"
"std::string_view grpcDescriptorSet() {\n"
"  return {reinterpret_cast<const char*>(kData), sizeof(kData)};\n"
"}\n"
"}  // namespace behaviorlib::reflection_internal\n")
