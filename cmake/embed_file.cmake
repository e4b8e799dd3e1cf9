# Writes the bytes of INPUT as a C++ array into OUTPUT, exposing
#   <NAMESPACE>::<FUNCTION>() -> std::string_view
# Usage: cmake -DINPUT=f -DOUTPUT=f.cc -DNAMESPACE=ns -DFUNCTION=fn [-DHEADER=h] -P embed_file.cmake
file(READ ${INPUT} _hex HEX)
string(LENGTH "${_hex}" _len)
math(EXPR _bytes "${_len} / 2")
string(REGEX REPLACE "([0-9a-f][0-9a-f])" "0x\\1," _arr "${_hex}")
string(REGEX REPLACE "(0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,)" "\\1\n" _arr "${_arr}")
set(_include "")
if(HEADER)
  set(_include "#include \"${HEADER}\"\n")
endif()
file(WRITE ${OUTPUT}
"// Generated from ${INPUT}; do not edit.\n"
"#include <string_view>\n"
"${_include}"
"namespace {\n"
"const unsigned char kData[${_bytes}] = {\n${_arr}\n};\n"
"}  // namespace\n"
"namespace ${NAMESPACE} {\n"
"std::string_view ${FUNCTION}();\n"
"std::string_view ${FUNCTION}() {\n"
"  return {reinterpret_cast<const char*>(kData), sizeof(kData)};\n"
"}\n"
"}  // namespace ${NAMESPACE}\n")
