# For builds against ROS 2 from PyPI wheels only: ./dev passes it to every interface package as
# -DCMAKE_PROJECT_INCLUDE (a ROS 2 install never reads it). Each message wheel's
# <pkg>::<pkg>__rosidl_generator_py target carries the include path of the machine that built the
# wheel (/opt/python/cp311-cp311/include/python3.11). At the end of the project, point every such
# imported target at this interpreter's headers and NumPy's.
function(_krang_pip_wheel_include_dirs)
  find_package(Python3 REQUIRED COMPONENTS Interpreter Development NumPy)
  get_property(targets DIRECTORY "${CMAKE_SOURCE_DIR}" PROPERTY IMPORTED_TARGETS)
  foreach(target IN LISTS targets)
    if(target MATCHES "__rosidl_generator_py$")
      set_target_properties(${target} PROPERTIES
        INTERFACE_INCLUDE_DIRECTORIES "${Python3_INCLUDE_DIRS};${Python3_NumPy_INCLUDE_DIRS}")
    endif()
  endforeach()
endfunction()
cmake_language(DEFER DIRECTORY "${CMAKE_SOURCE_DIR}" CALL _krang_pip_wheel_include_dirs)
