# The one build recipe of this repository's ROS 2 interface packages, msg/ (rg_interfaces) and
# msg_tf2/ (tf2_msgs): each CMakeLists.txt declares project() and includes this file by its real
# path (a symlinked colcon source still finds it), then calls rg_build_interfaces. They build with
# colcon on a full ROS 2 install, or with `pip install --no-build-isolation ./msg` (scikit-build-core)
# into a venv holding the ROS 2 PyPI wheels; the SKBUILD block and the include-dir fix work around
# what the wheels lack (../shared/notes/ros2-wheels.md in the dev notes). A macro, not a function:
# find_package, rosidl and ament_package must see and set the package directory's scope.
#
# rg_build_interfaces(FILES <.msg/.srv/.action ...> DEPENDENCIES <pkg ...> [ALSO_FIND <pkg ...>])
#   finds ament_cmake, rosidl_default_generators, DEPENDENCIES and ALSO_FIND (found, not passed to
#   rosidl), generates ${PROJECT_NAME}'s interfaces and calls ament_package().
macro(rg_build_interfaces)
  cmake_parse_arguments(_rg "" "" "FILES;DEPENDENCIES;ALSO_FIND" ${ARGN})
  enable_language(C CXX)

  if(DEFINED SKBUILD)
    # 1+2. The wheels install ament packages into the Python prefix (the venv), which CMake and
    # ament's resource index only search when told: CMAKE_PREFIX_PATH for find_package,
    # AMENT_PREFIX_PATH for rosidl's typesupport lookup at configure time.
    find_package(Python3 REQUIRED COMPONENTS Interpreter)
    execute_process(
      COMMAND "${Python3_EXECUTABLE}" -c "import sys; print(sys.prefix, end='')"
      OUTPUT_VARIABLE RG_PY_PREFIX RESULT_VARIABLE _rc)
    if(NOT _rc EQUAL 0 OR NOT EXISTS "${RG_PY_PREFIX}/share/ament_cmake")
      message(FATAL_ERROR "${PROJECT_NAME}: no ament_cmake under the Python prefix '${RG_PY_PREFIX}'; "
        "install requirements-ros-build.txt and build with pip --no-build-isolation")
    endif()
    list(PREPEND CMAKE_PREFIX_PATH "${RG_PY_PREFIX}")
    if(DEFINED ENV{AMENT_PREFIX_PATH} AND NOT "$ENV{AMENT_PREFIX_PATH}" STREQUAL "")
      set(ENV{AMENT_PREFIX_PATH} "${RG_PY_PREFIX}:$ENV{AMENT_PREFIX_PATH}")
    else()
      set(ENV{AMENT_PREFIX_PATH} "${RG_PY_PREFIX}")
    endif()
  endif()

  find_package(ament_cmake REQUIRED)
  find_package(rosidl_default_generators REQUIRED)
  foreach(_dep IN LISTS _rg_DEPENDENCIES _rg_ALSO_FIND)
    find_package(${_dep} REQUIRED)
  endforeach()

  # 3. The wheels' exported *__rosidl_generator_py targets carry the include dirs of the machine
  # that built them (/opt/python/...); point any non-existent ones at this interpreter's. Not only under
  # SKBUILD: a colcon build against the wheels hits it too; on a full ROS 2 install no path is missing.
  get_directory_property(_imported IMPORTED_TARGETS)
  foreach(_t IN LISTS _imported)
    get_target_property(_inc ${_t} INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT _inc)
      continue()
    endif()
    set(_missing FALSE)
    foreach(_d IN LISTS _inc)
      if(NOT _d MATCHES "^\\$<" AND NOT EXISTS "${_d}")
        set(_missing TRUE)
      endif()
    endforeach()
    if(_missing)
      find_package(Python3 REQUIRED COMPONENTS Interpreter Development.Module NumPy)
      message(STATUS "${PROJECT_NAME}: fixing include dirs of ${_t}")
      set_target_properties(${_t} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES
        "${Python3_INCLUDE_DIRS};${Python3_NumPy_INCLUDE_DIRS}")
    endif()
  endforeach()

  rosidl_generate_interfaces(${PROJECT_NAME} ${_rg_FILES} DEPENDENCIES ${_rg_DEPENDENCIES})
  ament_export_dependencies(rosidl_default_runtime)
  ament_package()
endmacro()
