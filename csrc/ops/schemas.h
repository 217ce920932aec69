// The operators' argument lists, spelled once: the library's schemas
// (schemas.cpp), their Python Autograd twins, and the benchmark's yardstick
// with fit_rotation's signature (../bench_ops.cpp).
#pragma once

#include "../fit_rotation.h"
#include "../limits.h"

#define TORCHROT_STRINGIFY_(x) #x
#define TORCHROT_STRINGIFY(x) TORCHROT_STRINGIFY_(x)
#define TORCHROT_GRADIENT_EPS_ARG "float gradient_eps=" TORCHROT_STRINGIFY(TORCHROT_DEFAULT_GRADIENT_EPS)
#define TORCHROT_FIT_OPTIONS_ARGS "int? max_iter=None, str variant=\"" TORCHROT_DEFAULT_VARIANT "\""
#define TORCHROT_FIT_ROTATION_SCHEMA \
  "(Tensor M, Tensor? init=None, " TORCHROT_FIT_OPTIONS_ARGS ", " TORCHROT_GRADIENT_EPS_ARG ") -> Tensor"
#define TORCHROT_FIT_ROTATION_INFO_SCHEMA \
  "(Tensor M, Tensor? init=None, " TORCHROT_FIT_OPTIONS_ARGS ") -> (Tensor R, Tensor iterations, Tensor status)"
#define TORCHROT_FIT_ROTATION_OUT_SCHEMA "(Tensor M, Tensor? init, int? max_iter, str variant, Tensor(a!) out) -> ()"
#define TORCHROT_FIT_ROTATION_BACKWARD_SCHEMA \
  "(Tensor grad, Tensor R, Tensor M, " TORCHROT_GRADIENT_EPS_ARG ") -> Tensor"
