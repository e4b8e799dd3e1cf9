# Writes INPUT as a C++ byte array into OUTPUT, exposing
#   behaviorlib::embedded::descriptorSet() -> std::string_view
file(READ ${INPUT} _hex HEX)
string(LENGTH "${_hex}" _len)
math(EXPR _bytes "${_len} / 2")
string(REGEX REPLACE "([0-9a-f][0-9a-f])" "0x\\1," _arr "${_hex}")
string(REGEX REPLACE "(0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,)" "\\1\n" _arr "${_arr}")
file(WRITE ${OUTPUT}
"// Generated from the behaviorlib descriptor set; do not edit.\n"
"#include <string_view>\n"
"#include \"behaviorlib/embedded_descriptors.h\"\n"
"namespace {\n"
"const unsigned char kData[${_bytes}] = {\n${_arr}\n};\n"
"}  // namespace\n"
"namespace behaviorlib::embedded {\n"
"std::string_view descriptorSet() {\n"
"  return {reinterpret_cast<const char*>(kData), sizeof(kData)};\n"
"}\n"
"}  // namespace behaviorlib::embedded\n")
