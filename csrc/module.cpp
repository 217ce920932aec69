// Makes the shared library importable as torchrot._C. Importing it runs the
// static initialisers of ops/schemas.cpp, ops/fit_rotation_cpu.cpp and
// autograd.cpp, which register torch.ops.torchrot.* and their kernels. Its
// Python functions: constants() hands the limits of limits.h, the status
// codes of fit_rotation.h and the messages of messages.h to the Python
// layers (torchrot/_constants.py), so that they are defined once;
// fit_rotation_eager() is the plain eager call of torchrot.fit_rotation; the
// _torch_internals_*() functions exist only for tests/test_torch_private.py,
// one per wrapper of torch_internals.h.
#include <Python.h>

#include <pybind11/pybind11.h>

#include <cstdint>
#include <initializer_list>
#include <iterator>
#include <optional>
#include <string>
#include <utility>

#include "fit_rotation.h"
#include "limits.h"
#include "messages.h"
#include "operators.h"
#define TORCHROT_TORCH_INTERNALS_PYTHON  // also the Python bindings' internals
#include "torch_internals.h"

namespace {

using torchrot::torch_internals::is_exact_tensor;
using torchrot::torch_internals::unpack_tensor;
using torchrot::torch_internals::wrap_tensor;

bool set_item(PyObject* dict, const char* key, PyObject* value) {
  if (value == nullptr) return false;
  const int failed = PyDict_SetItemString(dict, key, value);
  Py_DECREF(value);
  return failed == 0;
}

// {key: value} of Python objects made by `make` from each value; null on error.
template <class Value, class Make>
PyObject* dict_of(std::initializer_list<std::pair<const char*, Value>> items, Make make) {
  PyObject* dict = PyDict_New();
  if (dict == nullptr) return nullptr;
  for (const auto& [key, value] : items) {
    if (!set_item(dict, key, make(value))) {
      Py_DECREF(dict);
      return nullptr;
    }
  }
  return dict;
}

PyObject* status_codes() {
  using torchrot::FitStatus;
  const auto code = [](FitStatus status) { return PyLong_FromLong(static_cast<long>(status)); };
  return dict_of<FitStatus>({{"CAYLEY", FitStatus::kCayley},
                             {"FALLBACK", FitStatus::kFallback},
                             {"BAD_INIT", FitStatus::kBadInit},
                             {"NON_FINITE", FitStatus::kNonFinite}},
                            code);
}

// {key: template} of every message of messages.h, its static fields filled.
PyObject* messages() {
  using namespace torchrot::messages;
  PyObject* dict = PyDict_New();
  if (dict == nullptr) return nullptr;
  bool ok = set_item(dict, "OP_NAME", PyUnicode_FromString(kOpName)) &&
            set_item(dict, "BACKWARD_NAME", PyUnicode_FromString(kBackwardName)) &&
            set_item(dict, "ORTHOGONAL_NAME", PyUnicode_FromString(kOrthogonalName));
  for (const Message& message : kAll) {
    ok = ok && set_item(dict, message.key, PyUnicode_FromString(format(message).c_str()));
  }
  if (!ok) {
    Py_DECREF(dict);
    return nullptr;
  }
  return dict;
}

// A tuple of the n strings name(0), ..., name(n - 1).
template <class Name>
PyObject* tuple_of(size_t n, Name name) {
  PyObject* tuple = PyTuple_New(static_cast<Py_ssize_t>(n));
  if (tuple == nullptr) return nullptr;
  for (size_t i = 0; i < n; ++i) {
    const std::string text = name(i);
    PyObject* item = PyUnicode_FromString(text.c_str());
    if (item == nullptr) {
      Py_DECREF(tuple);
      return nullptr;
    }
    PyTuple_SET_ITEM(tuple, static_cast<Py_ssize_t>(i), item);
  }
  return tuple;
}

// The names of the variants, the supported dtypes ("float32", ...) and the
// CPU kernel objects, in their order.
PyObject* variant_names() {
  return tuple_of(std::size(torchrot::kVariantNames), [](size_t i) { return torchrot::kVariantNames[i].name; });
}

PyObject* dtype_names() {
  return tuple_of(std::size(torchrot::kSupportedDtypes),
                  [](size_t i) { return std::string(c10::getDtypeNames(torchrot::kSupportedDtypes[i]).first); });
}

PyObject* cpu_kernel_names() {
  return tuple_of(std::size(torchrot::kCpuKernelNames), [](size_t i) { return torchrot::kCpuKernelNames[i]; });
}

PyObject* constants(PyObject*, PyObject*) {
  using namespace torchrot::limits;
  PyObject* dict = PyDict_New();
  if (dict == nullptr) return nullptr;
  const bool ok = set_item(dict, "FIT_STATUS", status_codes()) && set_item(dict, "MESSAGES", messages()) &&
                  set_item(dict, "VARIANTS", variant_names()) &&
                  set_item(dict, "DEFAULT_VARIANT", PyUnicode_FromString(TORCHROT_DEFAULT_VARIANT)) &&
                  set_item(dict, "DTYPES", dtype_names()) && set_item(dict, "CPU_KERNELS", cpu_kernel_names()) &&
                  set_item(dict, "DEFAULT_GRADIENT_EPS", PyFloat_FromDouble(kDefaultGradientEps)) &&
                  set_item(dict, "MAX_GRADIENT_EPS", PyFloat_FromDouble(kMaxGradientEps)) &&
                  set_item(dict, "MAX_ITER", PyLong_FromLongLong(kMaxIter)) &&
                  set_item(dict, "INIT_TOLERANCE", PyFloat_FromDouble(kInitTolerance)) &&
                  set_item(dict, "INIT_CLEAN_EPS", PyFloat_FromDouble(kInitCleanEps)) &&
                  set_item(dict, "INIT_CLEAN_STEPS", PyLong_FromLong(kInitCleanSteps)) &&
                  set_item(dict, "LARGE_STEP", PyFloat_FromDouble(kLargeStep)) &&
                  set_item(dict, "STEPS_WITHOUT_CLEAN_UP", PyLong_FromLong(kStepsWithoutCleanUp)) &&
                  set_item(dict, "UNDAMPED_FLOAT", PyFloat_FromDouble(kUndampedFloat)) &&
                  set_item(dict, "UNDAMPED_DOUBLE", PyFloat_FromDouble(kUndampedDouble)) &&
                  set_item(dict, "OBJECTIVE_LAGUERRE_STEPS", PyLong_FromLong(kObjectiveLaguerreSteps)) &&
                  set_item(dict, "CONVERGED_CAP", PyLong_FromLong(kConvergedCap)) &&
                  set_item(dict, "MAX_ESCAPES", PyLong_FromLong(kMaxEscapes)) &&
                  set_item(dict, "GERSHGORIN_STEPS", PyLong_FromLong(kGershgorinSteps)) &&
                  set_item(dict, "ESTIMATE_SWITCH", PyFloat_FromDouble(kEstimateSwitch)) &&
                  set_item(dict, "MAX_CHECK_SLACK_EPS", PyFloat_FromDouble(kMaxCheckSlackEps));
  if (!ok) {
    Py_DECREF(dict);
    return nullptr;
  }
  return dict;
}

// fit_rotation_eager(M, init, max_iter, variant, gradient_eps, out): the
// operator torchrot::fit_rotation (its Autograd kernel: csrc/autograd.cpp), or
// torchrot::fit_rotation_out where out is a tensor, called through the
// dispatcher as torch.ops calls them (the GIL released around it), but without
// torch.ops' Python argument parsing and boxing, a large part of a one-matrix
// call's cost, with out= as well (benchmarks/lab_notes.md). The arguments are
// the operator's, already type-checked by torchrot.fit_rotation. Returns R, or
// out itself; or NotImplemented, before doing anything, where torch.ops would
// do more than call the operator or where an argument is not of the plain type
// it converts: a tensor subclass (its __torch_function__), an active torch
// function mode, max_iter beyond int64; the caller then calls the operator
// through torch.ops, which handles or rejects them.
PyObject* fit_rotation_eager(PyObject*, PyObject* const* args, Py_ssize_t nargs) {
  TORCHROT_BEGIN_TORCH_ERRORS
  if (nargs != 6 || !is_exact_tensor(args[0]) || (args[1] != Py_None && !is_exact_tensor(args[1])) ||
      (args[2] != Py_None && !PyLong_CheckExact(args[2])) || !PyUnicode_Check(args[3]) ||
      (args[5] != Py_None && !is_exact_tensor(args[5])) || torchrot::torch_internals::torch_function_mode_enabled()) {
    Py_RETURN_NOTIMPLEMENTED;
  }
  std::optional<int64_t> max_iter;
  if (args[2] != Py_None) {
    int overflow = 0;
    const long long value = PyLong_AsLongLongAndOverflow(args[2], &overflow);
    if (overflow != 0) Py_RETURN_NOTIMPLEMENTED;
    max_iter = value;
  }
  Py_ssize_t variant_size = 0;
  const char* variant_data = PyUnicode_AsUTF8AndSize(args[3], &variant_size);
  if (variant_data == nullptr) return nullptr;
  const c10::string_view variant(variant_data, static_cast<size_t>(variant_size));
  const double gradient_eps = PyFloat_AsDouble(args[4]);
  if (gradient_eps == -1.0 && PyErr_Occurred()) return nullptr;
  const at::Tensor M = unpack_tensor(args[0]);  // own references while the GIL is released
  std::optional<at::Tensor> init;
  if (args[1] != Py_None) init = unpack_tensor(args[1]);
  if (args[5] != Py_None) {
    static const auto op = torchrot::find_operator<torchrot::FitRotationOutSignature>("torchrot::fit_rotation_out");
    const at::Tensor out = unpack_tensor(args[5]);
    {
      pybind11::gil_scoped_release no_gil;
      op.call(M, init, max_iter, variant, out);
    }
    Py_INCREF(args[5]);
    return args[5];
  }
  static const auto op = torchrot::find_operator<torchrot::FitRotationSignature>("torchrot::fit_rotation");
  at::Tensor R;
  {
    pybind11::gil_scoped_release no_gil;
    R = op.call(M, init, max_iter, variant, gradient_eps);
  }
  return wrap_tensor(std::move(R));
  TORCHROT_END_TORCH_ERRORS
}

// Test-only: one function per wrapper of torch_internals.h, for
// tests/test_torch_private.py, which compares each with what torch itself
// says (Python's own private names, Tensor.view, torch's exceptions).

PyObject* bool_result(bool value) {
  if (value) Py_RETURN_TRUE;
  Py_RETURN_FALSE;
}

PyObject* internals_functorch_transforms_active(PyObject*, PyObject*) {
  return bool_result(torchrot::torch_internals::functorch_transforms_active());
}

PyObject* internals_forward_grad_mode_enabled(PyObject*, PyObject*) {
  return bool_result(torchrot::torch_internals::forward_grad_mode_enabled());
}

PyObject* internals_torch_function_mode_enabled(PyObject*, PyObject*) {
  return bool_result(torchrot::torch_internals::torch_function_mode_enabled());
}

// A tensor argument of a test function: null (a TypeError set) unless it is
// a plain tensor.
const at::Tensor* tensor_argument(PyObject* object) {
  if (is_exact_tensor(object)) return &unpack_tensor(object);
  PyErr_SetString(PyExc_TypeError, "expected a torch.Tensor");
  return nullptr;
}

// _torch_internals_forward_tangent(t): t's tangent at level 0, or None.
PyObject* internals_forward_tangent(PyObject*, PyObject* object) {
  TORCHROT_BEGIN_TORCH_ERRORS
  const at::Tensor* tensor = tensor_argument(object);
  if (tensor == nullptr) return nullptr;
  const at::Tensor& tangent = torchrot::torch_internals::forward_tangent(*tensor, /*level=*/0);
  if (!tangent.defined()) Py_RETURN_NONE;
  return wrap_tensor(tangent);
  TORCHROT_END_TORCH_ERRORS
}

// The int64 values of a Python sequence of ints; false (an error set) if it is not one.
bool int_sequence(PyObject* object, at::DimVector& values) {
  PyObject* items = PySequence_Fast(object, "expected a sequence of ints");
  if (items == nullptr) return false;
  const Py_ssize_t n = PySequence_Fast_GET_SIZE(items);
  for (Py_ssize_t i = 0; i < n; ++i) {
    const long long value = PyLong_AsLongLong(PySequence_Fast_GET_ITEM(items, i));
    if (value == -1 && PyErr_Occurred()) {
      Py_DECREF(items);
      return false;
    }
    values.push_back(value);
  }
  Py_DECREF(items);
  return true;
}

// _torch_internals_view_strides(sizes, strides, new_sizes): a tuple of
// strides, or None where no view exists.
PyObject* internals_view_strides(PyObject*, PyObject* args) {
  PyObject *sizes_object = nullptr, *strides_object = nullptr, *new_sizes_object = nullptr;
  if (!PyArg_ParseTuple(args, "OOO", &sizes_object, &strides_object, &new_sizes_object)) return nullptr;
  at::DimVector sizes, strides, new_sizes;
  if (!int_sequence(sizes_object, sizes) || !int_sequence(strides_object, strides) ||
      !int_sequence(new_sizes_object, new_sizes)) {
    return nullptr;
  }
  TORCHROT_BEGIN_TORCH_ERRORS
  const auto view = torchrot::torch_internals::view_strides(sizes, strides, new_sizes);
  if (!view.has_value()) Py_RETURN_NONE;
  PyObject* tuple = PyTuple_New(static_cast<Py_ssize_t>(view->size()));
  if (tuple == nullptr) return nullptr;
  for (size_t i = 0; i < view->size(); ++i) {
    PyObject* item = PyLong_FromLongLong((*view)[i]);
    if (item == nullptr) {
      Py_DECREF(tuple);
      return nullptr;
    }
    PyTuple_SET_ITEM(tuple, static_cast<Py_ssize_t>(i), item);
  }
  return tuple;
  TORCHROT_END_TORCH_ERRORS
}

PyObject* internals_is_exact_tensor(PyObject*, PyObject* object) { return bool_result(is_exact_tensor(object)); }

// _torch_internals_unpack_tensor(t): (t's data pointer, its sizes), read
// from the unpacked at::Tensor.
PyObject* internals_unpack_tensor(PyObject*, PyObject* object) {
  TORCHROT_BEGIN_TORCH_ERRORS
  const at::Tensor* tensor = tensor_argument(object);
  if (tensor == nullptr) return nullptr;
  PyObject* pointer = PyLong_FromVoidPtr(tensor->data_ptr());
  if (pointer == nullptr) return nullptr;
  PyObject* sizes = PyTuple_New(tensor->dim());
  for (int64_t d = 0; sizes != nullptr && d < tensor->dim(); ++d) {
    PyObject* item = PyLong_FromLongLong(tensor->size(d));
    if (item == nullptr) Py_CLEAR(sizes);
    if (item != nullptr) PyTuple_SET_ITEM(sizes, static_cast<Py_ssize_t>(d), item);
  }
  if (sizes == nullptr) {
    Py_DECREF(pointer);
    return nullptr;
  }
  return Py_BuildValue("(NN)", pointer, sizes);
  TORCHROT_END_TORCH_ERRORS
}

// _torch_internals_wrap_tensor(t): (t's tensor wrapped again, which is t
// itself; a copy of it wrapped, a new torch.Tensor).
PyObject* internals_wrap_tensor(PyObject*, PyObject* object) {
  TORCHROT_BEGIN_TORCH_ERRORS
  const at::Tensor* tensor = tensor_argument(object);
  if (tensor == nullptr) return nullptr;
  PyObject* same = wrap_tensor(*tensor);
  if (same == nullptr) return nullptr;
  PyObject* copy = wrap_tensor(tensor->clone());
  if (copy == nullptr) {
    Py_DECREF(same);
    return nullptr;
  }
  return Py_BuildValue("(NN)", same, copy);
  TORCHROT_END_TORCH_ERRORS
}

// _torch_internals_raise(kind): throws TORCH_CHECK's error of that kind
// ("runtime", "value", "type", "index") or, for "warn", warns with TORCH_WARN
// and returns None, between TORCHROT_BEGIN_TORCH_ERRORS and its end.
PyObject* internals_raise(PyObject*, PyObject* object) {
  TORCHROT_BEGIN_TORCH_ERRORS
  const char* kind = PyUnicode_AsUTF8(object);
  if (kind == nullptr) return nullptr;
  const std::string k(kind);
  TORCH_CHECK(k != "runtime", "torchrot test error: runtime");
  TORCH_CHECK_VALUE(k != "value", "torchrot test error: value");
  TORCH_CHECK_TYPE(k != "type", "torchrot test error: type");
  TORCH_CHECK_INDEX(k != "index", "torchrot test error: index");
  if (k == "warn") TORCH_WARN("torchrot test warning");
  Py_RETURN_NONE;
  TORCHROT_END_TORCH_ERRORS
}

PyMethodDef methods[] = {
    {"constants", constants, METH_NOARGS,
     "The limits, defaults and tolerances of csrc/limits.h, the status codes and the shared messages, by name."},
    {"fit_rotation_eager", reinterpret_cast<PyCFunction>(reinterpret_cast<void (*)(void)>(fit_rotation_eager)),
     METH_FASTCALL, "torchrot::fit_rotation(_out) for torchrot.fit_rotation's plain eager call."},
    // Test-only (tests/test_torch_private.py): the wrappers of torch_internals.h.
    {"_torch_internals_functorch_transforms_active", internals_functorch_transforms_active, METH_NOARGS, nullptr},
    {"_torch_internals_forward_grad_mode_enabled", internals_forward_grad_mode_enabled, METH_NOARGS, nullptr},
    {"_torch_internals_torch_function_mode_enabled", internals_torch_function_mode_enabled, METH_NOARGS, nullptr},
    {"_torch_internals_forward_tangent", internals_forward_tangent, METH_O, nullptr},
    {"_torch_internals_view_strides", internals_view_strides, METH_VARARGS, nullptr},
    {"_torch_internals_is_exact_tensor", internals_is_exact_tensor, METH_O, nullptr},
    {"_torch_internals_unpack_tensor", internals_unpack_tensor, METH_O, nullptr},
    {"_torch_internals_wrap_tensor", internals_wrap_tensor, METH_O, nullptr},
    {"_torch_internals_raise", internals_raise, METH_O, nullptr},
    {nullptr, nullptr, 0, nullptr},
};

}  // namespace

extern "C" PyMODINIT_FUNC PyInit__C(void) {
  static PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_C", "torchrot operator library", -1, methods};
  return PyModule_Create(&module_def);
}
