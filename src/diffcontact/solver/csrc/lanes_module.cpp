// The lane-parallel interior-point kernel as a CPython extension module, diffcontact.solver._lanes (see kernel.py;
// the entry points' arguments are the structs of api.h).  The instruction set is chosen at run time, so one build
// runs on any x86-64 CPU (or on any other, with 2 lanes).
//
// Each entry point takes the arrays through the buffer protocol (C-contiguous; sizes checked against B, K, d) and
// the scalars as Python numbers (METH_FASTCALL: about a µs a call, against three for ctypes with the arguments
// packed in Python), fills the struct and runs the kernel on elements start … stop − 1 without the GIL, so that
// lanes.parallel can split a batch among threads.
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include "api.h"

#define DECLARE(NS)                                         \
  namespace NS {                                            \
  int solve(const SolveArgs& a, i64 start, i64 stop);       \
  int adjoint(const AdjointArgs& a, i64 start, i64 stop);   \
  int flat(const FlatArgs& a, i64 start, i64 stop);         \
  }
DECLARE(isa_base)
#if defined(__x86_64__)
DECLARE(isa_avx2)
DECLARE(isa_avx512)
#endif

static int (*solve_fn)(const SolveArgs&, i64, i64) = isa_base::solve;
static int (*adjoint_fn)(const AdjointArgs&, i64, i64) = isa_base::adjoint;
static int (*flat_fn)(const FlatArgs&, i64, i64) = isa_base::flat;

// Lane widths this CPU can run, best first: a bit set of 8, 4, 2.
static int supported_widths() {
  int s = 2;
#if defined(__x86_64__)
  __builtin_cpu_init();
  if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma")) s |= 4;
  if ((s & 4) && __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq") &&
      __builtin_cpu_supports("avx512vl"))
    s |= 8;
#endif
  return s;
}

// ---- argument parsing ----

// The buffers of one call, released together.
struct Buffers {
  Py_buffer v[16];
  int held = 0;
  ~Buffers() {
    for (int i = 0; i < held; i++) PyBuffer_Release(&v[i]);
  }
  // args[i] as a C-contiguous buffer of items of `itemsize` bytes, at least `items` of them (exactly, if exact);
  // null with a Python error set otherwise.
  void* get(PyObject* const* args, int i, const char* name, Py_ssize_t itemsize, i64 items, bool writable,
            bool exact = false) {
    Py_buffer* b = &v[held];
    if (PyObject_GetBuffer(args[i], b, writable ? PyBUF_WRITABLE : PyBUF_SIMPLE) < 0) return nullptr;
    held++;
    if (b->itemsize != itemsize || (exact ? b->len != items * itemsize : b->len < items * itemsize)) {
      PyErr_Format(PyExc_ValueError, "contact solver kernel: %s has %zd bytes of %zd-byte items, needs %s%lld items",
                   name, b->len, b->itemsize, exact ? "" : "at least ", items);
      return nullptr;
    }
    return b->buf;
  }
};

static bool get_int(PyObject* o, i64* out) {
  *out = PyLong_AsLongLong(o);
  return !(*out == -1 && PyErr_Occurred());
}
static bool get_double(PyObject* o, double* out) {
  *out = PyFloat_AsDouble(o);
  return !(*out == -1.0 && PyErr_Occurred());
}

static bool check_nargs(Py_ssize_t nargs, Py_ssize_t want, const char* fn) {
  if (nargs == want) return true;
  PyErr_Format(PyExc_TypeError, "_lanes.%s takes %zd arguments, got %zd", fn, want, nargs);
  return false;
}

// K, d and the element range; B is the number of problems (from the length of an array of B·K items).
static bool check_shape(i64 K, i64 d, i64 start, i64 stop, i64 B) {
  if (K < 1 || d < 1 || d > 3) {
    PyErr_Format(PyExc_ValueError, "contact solver kernel: K = %lld, d = %lld (need K >= 1, d in 1, 2, 3)", K, d);
    return false;
  }
  if (start < 0 || stop < start || stop > B) {
    PyErr_Format(PyExc_ValueError, "contact solver kernel: elements %lld ... %lld of %lld", start, stop, B);
    return false;
  }
  return true;
}

// Run the kernel without the GIL; returns whether it failed (its return code then a Python error).
template <class Args>
static bool failed(int (*fn)(const Args&, i64, i64), const Args& a, i64 start, i64 stop, i64 K) {
  int rc;
  Py_BEGIN_ALLOW_THREADS;
  rc = fn(a, start, stop);
  Py_END_ALLOW_THREADS;
  if (rc == -1) PyErr_Format(PyExc_MemoryError, "contact solver kernel: out of memory for K = %lld", K);
  if (rc != 0 && rc != -1) PyErr_Format(PyExc_RuntimeError, "contact solver kernel failed (code %d)", rc);
  return rc != 0;
}

// The outputs of the solve in one buffer (lanes.IPMResult: z, s_l, lam_l, s_q, lam_q, status, iterations, residual,
// in this order, B rows each) into a; returns null (a Python error set) unless `out` holds exactly that many items.
static void* outputs(Buffers& bufs, PyObject* const* args, int i, i64 B, i64 K, i64 n, SolveArgs& a) {
  double* p = (double*)bufs.get(args, i, "out", 8, B * (3 * n + 2 * K + 3), true, true);
  if (!p) return nullptr;
  a.z = p, a.s_l = p + B * n, a.lam_l = a.s_l + B * K, a.s_q = a.lam_l + B * K, a.lam_q = a.s_q + B * n;
  a.status = (i64*)(a.lam_q + B * n), a.iterations = a.status + B, a.residual = (double*)(a.iterations + B);
  return p;
}

// solve(A, T, c, lower, on, on_l, idx, trace, out, K, d, ipm_tol, final_tol, acceptable_tol, max_iter,
//       start_margin, refine_tol, polish_steps, start, stop) -> None: SolveArgs on the elements idx[start:stop];
// the outputs in `out` (see outputs), trace (B, T, 4) or empty.
static PyObject* py_solve(PyObject*, PyObject* const* args, Py_ssize_t nargs) {
  if (!check_nargs(nargs, 20, "solve")) return nullptr;
  SolveArgs a{};
  i64 start, stop;
  if (!get_int(args[9], &a.K) || !get_int(args[10], &a.d) || !get_double(args[11], &a.ipm_tol) ||
      !get_double(args[12], &a.final_tol) || !get_double(args[13], &a.acceptable_tol) ||
      !get_int(args[14], &a.max_iter) || !get_double(args[15], &a.start_margin) ||
      !get_double(args[16], &a.refine_tol) || !get_int(args[17], &a.polish_steps) || !get_int(args[18], &start) ||
      !get_int(args[19], &stop))
    return nullptr;
  Buffers bufs;
  const i64 K = a.K, n = K * a.d;
  if (!(a.lower = (const double*)bufs.get(args, 3, "lower", 8, 0, false))) return nullptr;
  const i64 B = K > 0 ? (i64)(bufs.v[0].len / 8) / K : 0;
  Py_buffer* idx = &bufs.v[bufs.held];
  if (!(a.idx = (const i64*)bufs.get(args, 6, "idx", 8, 0, false))) return nullptr;
  if (!check_shape(K, a.d, start, stop, idx->len / 8)) return nullptr;
  for (i64 j = start; j < stop; j++)
    if (a.idx[j] < 0 || a.idx[j] >= B)
      return PyErr_Format(PyExc_ValueError, "contact solver kernel: element %lld of %lld", a.idx[j], B);
  if (!(a.A = (const double*)bufs.get(args, 0, "A", 8, B * n * n, false)) ||
      !(a.scale = (const double*)bufs.get(args, 1, "T", 8, B * n, false)) ||
      !(a.c = (const double*)bufs.get(args, 2, "c", 8, B * n, false)) ||
      !(a.on = (const unsigned char*)bufs.get(args, 4, "on", 1, B * K, false)) ||
      !(a.on_l = (const unsigned char*)bufs.get(args, 5, "on_l", 1, B * K, false)))
    return nullptr;
  Py_buffer* trace = &bufs.v[bufs.held];
  if (!(a.trace = (double*)bufs.get(args, 7, "trace", 8, 0, true))) return nullptr;
  a.T = trace->len && B ? trace->len / (8 * 4 * B) : 0;
  if (a.T * 4 * B * 8 != trace->len)
    return PyErr_Format(PyExc_ValueError, "contact solver kernel: trace has %zd bytes, not (B, T, 4)", trace->len);
  if (!outputs(bufs, args, 8, B, K, n, a) || failed(solve_fn, a, start, stop, K)) return nullptr;
  Py_RETURN_NONE;
}

// adjoint(A, T, out, on, on_l, g, u, v_l, ok, K, d, start, stop) -> None: AdjointArgs at the solution held in
// `out` (the solve's outputs), for elements start … stop − 1.
static PyObject* py_adjoint(PyObject*, PyObject* const* args, Py_ssize_t nargs) {
  if (!check_nargs(nargs, 13, "adjoint")) return nullptr;
  AdjointArgs a{};
  i64 start, stop;
  if (!get_int(args[9], &a.K) || !get_int(args[10], &a.d) || !get_int(args[11], &start) || !get_int(args[12], &stop))
    return nullptr;
  Buffers bufs;
  const i64 K = a.K, n = K * a.d;
  if (!(a.ok = (unsigned char*)bufs.get(args, 8, "ok", 1, 0, true))) return nullptr;
  const i64 B = bufs.v[0].len;
  SolveArgs s{};
  if (!check_shape(K, a.d, start, stop, B) || !outputs(bufs, args, 2, B, K, n, s)) return nullptr;
  a.s_l = s.s_l, a.lam_l = s.lam_l, a.s_q = s.s_q, a.lam_q = s.lam_q;
  if (!(a.A = (const double*)bufs.get(args, 0, "A", 8, B * n * n, false)) ||
      !(a.scale = (const double*)bufs.get(args, 1, "T", 8, B * n, false)) ||
      !(a.on = (const unsigned char*)bufs.get(args, 3, "on", 1, B * K, false)) ||
      !(a.on_l = (const unsigned char*)bufs.get(args, 4, "on_l", 1, B * K, false)) ||
      !(a.g = (const double*)bufs.get(args, 5, "g", 8, B * n, false)) ||
      !(a.u = (double*)bufs.get(args, 6, "u", 8, B * n, true)) ||
      !(a.v_l = (double*)bufs.get(args, 7, "v_l", 8, B * K, true)))
    return nullptr;
  if (failed(adjoint_fn, a, start, stop, K)) return nullptr;
  Py_RETURN_NONE;
}

// flat(A, mu, active, flags, K, d, tol, start, stop) -> None: FlatArgs for elements start … stop − 1; flags
// (3, B) bool receives flat, finite and symmetric.
static PyObject* py_flat(PyObject*, PyObject* const* args, Py_ssize_t nargs) {
  if (!check_nargs(nargs, 9, "flat")) return nullptr;
  FlatArgs a{};
  i64 start, stop;
  if (!get_int(args[4], &a.K) || !get_int(args[5], &a.d) || !get_double(args[6], &a.tol) ||
      !get_int(args[7], &start) || !get_int(args[8], &stop))
    return nullptr;
  Buffers bufs;
  const i64 K = a.K, n = K * a.d;
  if (!(a.flat = (unsigned char*)bufs.get(args, 3, "flags", 1, 0, true))) return nullptr;
  const i64 B = bufs.v[0].len / 3;
  a.finite = a.flat + B, a.symmetric = a.finite + B;
  if (3 * B != bufs.v[0].len)
    return PyErr_Format(PyExc_ValueError, "contact solver kernel: flags has %zd bytes, not (3, B)", bufs.v[0].len);
  if (!check_shape(K, a.d, start, stop, B) || !(a.A = (const double*)bufs.get(args, 0, "A", 8, B * n * n, false)) ||
      !(a.mu = (const double*)bufs.get(args, 1, "mu", 8, B * K, false)) ||
      !(a.active = (const unsigned char*)bufs.get(args, 2, "active", 1, B * K, false)) ||
      failed(flat_fn, a, start, stop, K))
    return nullptr;
  Py_RETURN_NONE;
}

// constants() -> dict: the facts of api.h, for kernel.py to check its copies against.
static PyObject* py_constants(PyObject*, PyObject* const*, Py_ssize_t) {
  return Py_BuildValue("{s:L,s:i,s:i,s:i,s:i,s:i,s:i,s:d}", "api_version", (long long)API_VERSION, "converged",
                       CONVERGED, "inaccurate", INACCURATE, "max_iter", MAX_ITER, "numerical", NUMERICAL, "unbounded",
                       UNBOUNDED, "first_failure", FIRST_FAILURE, "weak_tol", WEAK_TOL);
}

// supported() -> int: the bit set of lane widths this CPU runs (8, 4, 2).
static PyObject* py_supported(PyObject*, PyObject* const*, Py_ssize_t) { return PyLong_FromLong(supported_widths()); }

// select(w) -> int: use the kernel of lane width w; returns it, or 0 if this CPU cannot run it.
static PyObject* py_select(PyObject*, PyObject* const* args, Py_ssize_t nargs) {
  i64 w;
  if (!check_nargs(nargs, 1, "select") || !get_int(args[0], &w)) return nullptr;
  if (!(w == 8 || w == 4 || w == 2) || !(supported_widths() & w)) return PyLong_FromLong(0);
#if defined(__x86_64__)
  if (w == 8) solve_fn = isa_avx512::solve, adjoint_fn = isa_avx512::adjoint, flat_fn = isa_avx512::flat;
  if (w == 4) solve_fn = isa_avx2::solve, adjoint_fn = isa_avx2::adjoint, flat_fn = isa_avx2::flat;
#endif
  if (w == 2) solve_fn = isa_base::solve, adjoint_fn = isa_base::adjoint, flat_fn = isa_base::flat;
  return PyLong_FromLong((long)w);
}

#define FAST(name, fn, doc) {name, (PyCFunction)(void (*)(void))fn, METH_FASTCALL, doc}
static PyMethodDef methods[] = {
    FAST("solve", py_solve, "The interior-point method with polishing (SolveArgs of api.h)."),
    FAST("adjoint", py_adjoint, "The adjoint solve of the backward pass (AdjointArgs of api.h)."),
    FAST("flat", py_flat, "The test for flat directions (FlatArgs of api.h)."),
    FAST("constants", py_constants, "The facts of api.h kernel.py checks."),
    FAST("supported", py_supported, "Lane widths this CPU runs, as a bit set."),
    FAST("select", py_select, "Use the kernel of this lane width."),
    {nullptr, nullptr, 0, nullptr},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_lanes", "The contact solver's compiled kernel.", -1,
                                    methods};

PyMODINIT_FUNC PyInit__lanes(void) { return PyModule_Create(&module); }
