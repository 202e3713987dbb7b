# Included at the end of llama.cpp's project() when scripts/bootstrap.sh builds llama-cpp-python
# (CMAKE_PROJECT_llama.cpp_INCLUDE): llama-cpp-python forces on llama.cpp's common library, which only
# llama.cpp's own tools use and the Python package neither links nor installs. A normal variable in
# llama.cpp's scope turns it off there (option() keeps it: policy CMP0077), a third of the compile.
set(LLAMA_BUILD_COMMON OFF)
