# The Stanford bunny, armadillo and Chinese dragon ship inside Debian's libcgal-demo package
# (data.tar.gz, data/meshes/*.off). They are extracted into the build tree at configure time and
# installed with the tools; they are never committed to the project.

set(PRISM_CGAL_DATA_TARBALL "/usr/share/doc/libcgal-dev/data.tar.gz" CACHE FILEPATH
    "libcgal-demo's data archive holding data/meshes/*.off")
set(PRISM_MESH_BUILD_DIR "${CMAKE_BINARY_DIR}/share/prism/meshes")
set(PRISM_MESH_INSTALL_DIR "${CMAKE_INSTALL_PREFIX}/share/prism/meshes")
set(_prism_meshes bunny00.off armadillo.off ChineseDragon-10kv.off)

if(EXISTS "${PRISM_CGAL_DATA_TARBALL}")
  set(_missing FALSE)
  foreach(m ${_prism_meshes})
    if(NOT EXISTS "${PRISM_MESH_BUILD_DIR}/${m}")
      set(_missing TRUE)
    endif()
  endforeach()
  if(_missing)
    set(_tmp "${CMAKE_BINARY_DIR}/_cgal_data")
    file(MAKE_DIRECTORY "${_tmp}" "${PRISM_MESH_BUILD_DIR}")
    set(_members)
    foreach(m ${_prism_meshes})
      list(APPEND _members "data/meshes/${m}")
    endforeach()
    execute_process(COMMAND ${CMAKE_COMMAND} -E tar xzf "${PRISM_CGAL_DATA_TARBALL}" ${_members}
                    WORKING_DIRECTORY "${_tmp}" RESULT_VARIABLE _rc)
    if(_rc EQUAL 0)
      foreach(m ${_prism_meshes})
        file(COPY "${_tmp}/data/meshes/${m}" DESTINATION "${PRISM_MESH_BUILD_DIR}")
      endforeach()
    else()
      message(WARNING "Could not extract meshes from ${PRISM_CGAL_DATA_TARBALL}; mesh presets will fail")
    endif()
    file(REMOVE_RECURSE "${_tmp}")
  endif()
else()
  message(WARNING "libcgal-demo not installed (${PRISM_CGAL_DATA_TARBALL}); mesh presets need --mesh-dir")
endif()
