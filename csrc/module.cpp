// Makes the shared library importable as torchrot._C. Importing it runs the
// static initialisers of ops.cpp, which register torch.ops.torchrot.*. Its one
// Python function, constants(), hands the limits of limits.h to the Python
// layers (torchrot/_limits.py), so that they are defined once.
#include <Python.h>

#include "limits.h"

namespace {

bool set_item(PyObject* dict, const char* key, PyObject* value) {
  if (value == nullptr) return false;
  const int failed = PyDict_SetItemString(dict, key, value);
  Py_DECREF(value);
  return failed == 0;
}

PyObject* constants(PyObject*, PyObject*) {
  using namespace torchrot::limits;
  PyObject* dict = PyDict_New();
  if (dict == nullptr) return nullptr;
  const bool ok = set_item(dict, "DEFAULT_GRADIENT_EPS", PyFloat_FromDouble(kDefaultGradientEps)) &&
                  set_item(dict, "MAX_GRADIENT_EPS", PyFloat_FromDouble(kMaxGradientEps)) &&
                  set_item(dict, "MAX_ITER", PyLong_FromLongLong(kMaxIter)) &&
                  set_item(dict, "INIT_TOLERANCE", PyFloat_FromDouble(kInitTolerance)) &&
                  set_item(dict, "INIT_CLEAN_FLOAT", PyFloat_FromDouble(kInitCleanFloat)) &&
                  set_item(dict, "INIT_CLEAN_DOUBLE", PyFloat_FromDouble(kInitCleanDouble)) &&
                  set_item(dict, "INIT_CLEAN_STEPS", PyLong_FromLong(kInitCleanSteps)) &&
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

PyMethodDef methods[] = {
    {"constants", constants, METH_NOARGS, "The limits, defaults and tolerances of csrc/limits.h, by name."},
    {nullptr, nullptr, 0, nullptr},
};

}  // namespace

extern "C" PyMODINIT_FUNC PyInit__C(void) {
  static PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_C", "torchrot operator library", -1, methods};
  return PyModule_Create(&module_def);
}
