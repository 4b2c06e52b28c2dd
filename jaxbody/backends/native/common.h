
#include <cstdint>
using T = @T@;
constexpr int MAX_IN = 24, MAX_OUT = 8;
// operand k of state b: x[k] + b * s[k] (rows of a (batch, n) array; s = 0: shared by all
// states); result j of state b: y[j] + b * n[j]
struct Inputs {
  const T* x[MAX_IN];
  int64_t s[MAX_IN];
  T* y[MAX_OUT];
  int64_t n[MAX_OUT];
};
typedef void (*Range)(const Inputs*, int64_t, int64_t);
