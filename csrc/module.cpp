// Makes the shared library importable as torchrot._C. Importing it runs the
// static initialisers of ops.cpp, which register torch.ops.torchrot.*; the
// module itself has no Python functions.
#include <Python.h>

extern "C" PyMODINIT_FUNC PyInit__C(void) {
  static PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_C", "torchrot operator library", -1, nullptr};
  return PyModule_Create(&module_def);
}
