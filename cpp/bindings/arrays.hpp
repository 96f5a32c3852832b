// The one array convention of the bindings.
//
// Inputs: In<T> for every array argument, T one of the aliases in tpscore/types.hpp
// (or another plain Eigen matrix). It is a read-only view of the caller's NumPy array,
// never a copy: nanobind accepts only an array whose dtype and memory order already
// match T (C-contiguous for the row-major aliases), and refuses anything else with a
// TypeError instead of converting it silently. The Python kernel modules validate and
// convert first, so a refusal here means a missed conversion there. A view passes to a
// kernel's Eigen::Ref<const T> parameter without a copy.
//
// Outputs: owning Eigen values (or a std::tuple of them). nanobind moves a returned
// Eigen matrix into a NumPy array without copying its data; a kernel that writes
// through a pointer gets the data() of an Eigen matrix the binding allocates and
// returns.
#pragma once

#include <nanobind/eigen/dense.h>

#include <Eigen/Core>

#include "tpscore/types.hpp"

namespace tpscore_bindings {

/// A validated NumPy array, viewed in place.
template <class T>
using In = Eigen::Map<const T>;

}  // namespace tpscore_bindings
