
// The dense output of an RK4 step [tprev, tnext] (jaxbody.simulation.RK4Stages): diffrax's
// ThirdOrderHermitePolynomialInterpolation.from_k with k = (k1, k4), the first and last stage
// increments (h f). With a = k1 + k4 + 2 y0 − 2 y1 and b = −2 k1 − k4 − 3 y0 + 3 y1 it is the
// cubic y(θ) = ((a θ + b) θ + k1) θ + y0, evaluated as jnp.polyval does, at
// θ = (t − tprev) / (tnext − tprev) (diffrax's linear_rescale: 0 for a step of length zero).
// (X: a scalar T, or V for a block of lanes.)
template <class X>
static inline X hermite_theta(X tprev, X t, X tnext) {
  return tprev == tnext ? X{} : (t - tprev) / (tnext - tprev);
}

template <class X>
static inline X hermite(X y0, X y1, X k1, X k4, X theta) {
  const X a = k1 + k4 + T(2) * y0 - T(2) * y1;
  const X b = -T(2) * k1 - k4 - T(3) * y0 + T(3) * y1;
  return ((a * theta + b) * theta + k1) * theta + y0;
}

// The derivatives of y(θ) with respect to (y0, y1, k1, k4): the cubic Hermite basis
// (2θ³ − 3θ² + 1, −2θ³ + 3θ², θ³ − 2θ² + θ, θ³ − θ²); the reverse sweep multiplies a saved
// state's cotangent by them.
static inline void hermite_weights(T theta, T* w) {
  const T t2 = theta * theta, t3 = t2 * theta;
  w[0] = T(2) * t3 - T(3) * t2 + T(1);
  w[1] = T(3) * t2 - T(2) * t3;
  w[2] = t3 - T(2) * t2 + theta;
  w[3] = t3 - t2;
}
