// Makes the shared library importable as torchrot._C. Importing it runs the
// static initialisers of ops.cpp, which register torch.ops.torchrot.*. Its
// Python functions: constants() hands the limits of limits.h, the status
// codes of fit_rotation.h and the messages of messages.h to the Python
// layers (torchrot/_constants.py), so that they are defined once;
// fit_rotation_eager() is the plain eager call of torchrot.fit_rotation.
#include <Python.h>

#include <torch/csrc/Exceptions.h>
#include <torch/csrc/autograd/python_variable.h>
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
#include "torch_internals.h"

namespace {

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
// operator torchrot::fit_rotation (its Autograd kernel: csrc/autograd.cpp),
// or torchrot::fit_rotation_out where out is a tensor, called through the
// dispatcher as torch.ops calls them (the GIL released around it), but
// without torch.ops' Python argument parsing and boxing, which cost more than
// half of a one-matrix call on this project's VM (12.2 against 5.7 us; with
// out, 3.6 against 2.4). The arguments are the operator's, already
// type-checked by torchrot.fit_rotation. Returns R, or out itself; or
// NotImplemented, before doing anything, where torch.ops would do more than
// call the operator or where an argument is not of the plain type it
// converts: a tensor subclass (its __torch_function__), an active torch
// function mode, max_iter beyond int64; the caller then calls the operator
// through torch.ops, which handles or rejects them.
PyObject* fit_rotation_eager(PyObject*, PyObject* const* args, Py_ssize_t nargs) {
  HANDLE_TH_ERRORS
  if (nargs != 6 || !THPVariable_CheckExact(args[0]) || (args[1] != Py_None && !THPVariable_CheckExact(args[1])) ||
      (args[2] != Py_None && !PyLong_CheckExact(args[2])) || !PyUnicode_Check(args[3]) ||
      (args[5] != Py_None && !THPVariable_CheckExact(args[5])) ||
      torchrot::torch_internals::torch_function_mode_enabled()) {
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
  const at::Tensor M = THPVariable_Unpack(args[0]);  // own references while the GIL is released
  std::optional<at::Tensor> init;
  if (args[1] != Py_None) init = THPVariable_Unpack(args[1]);
  if (args[5] != Py_None) {
    static const auto op = torchrot::find_operator<torchrot::FitRotationOutSignature>("torchrot::fit_rotation_out");
    const at::Tensor out = THPVariable_Unpack(args[5]);
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
  return THPVariable_Wrap(std::move(R));
  END_HANDLE_TH_ERRORS
}

PyMethodDef methods[] = {
    {"constants", constants, METH_NOARGS,
     "The limits, defaults and tolerances of csrc/limits.h, the status codes and the shared messages, by name."},
    {"fit_rotation_eager", reinterpret_cast<PyCFunction>(reinterpret_cast<void (*)(void)>(fit_rotation_eager)),
     METH_FASTCALL, "torchrot::fit_rotation(_out) for torchrot.fit_rotation's plain eager call."},
    {nullptr, nullptr, 0, nullptr},
};

}  // namespace

extern "C" PyMODINIT_FUNC PyInit__C(void) {
  static PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_C", "torchrot operator library", -1, methods};
  return PyModule_Create(&module_def);
}
