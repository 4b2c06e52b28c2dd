
// A whole adaptive solve per block of states (jaxbody.backends.native.adaptive): each lane its
// own times, step size, controller state, step counts, saved times and result code; the block
// ends when every lane is done. The steps and the saves are diffrax's (see adaptive_attempt.cc).
@HELPERS@

static void adaptive_block(const Inputs& in, int64_t b0, int n) {
@ACCESS@
@INVARIANT@
  constexpr int NQ = @NQ@, NV = @NV@, NW = @NW@, N = NQ + NV + NW, S = @S@, D = @D@;
  static const T A[S][S] = @A@;
  static const T E[S] = @E@;
  static const T P[S][D] = @P@;
  static const T C[S] = @C@;
  // the schedule (operand 10): per lane, or the same for all (flags: lane 0's)
  const U t0 = ld(10, 0), t1 = ld(10, 1), t1_floor = ld(10, 2), max_steps = ld(10, 3), dt0 = ld(10, 4);
  const U rtol = ld(10, 5), atol = ld(10, 6), dtmin = ld(10, 10), dtmax = ld(10, 11);
  const T pcoeff = ld(10, 7)[0], icoeff = ld(10, 8)[0], dcoeff = ld(10, 9)[0], order = ld(10, 16)[0];
  const bool force_dtmin = ld(10, 12)[0] != T(0), has_dtmin = ld(10, 20)[0] != T(0);
  // the works the solve carries (bit j: the program's work j, the powers of the field in order)
  const int64_t works = int64_t(ld(10, 18)[0]);
  auto tracked = [works](int j) { return ((works >> j) & 1) != 0; };
  const T factormin = ld(10, 13)[0], factormax = ld(10, 14)[0], safety = ld(10, 15)[0];
  const I frozen = ld(10, 17) != T(0);
  const int64_t every = int64_t(ld(10, 19)[0]), n_ts = int64_t(ld(10, 21)[0]);
  const T c1 = (icoeff + pcoeff + dcoeff) / order, c2 = -(pcoeff + T(2) * dcoeff) / order, c3 = dcoeff / order;
  int count = NQ + NV;
  for (int j = 0; j < NW; ++j) count += tracked(j) ? 1 : 0;
  // the field (q̇, a, P) at time t and a state of N values (q, v, w); a frozen lane (an input that
  // failed simulate's checks) has none, and a work the solve does not carry stays put
  auto evaluate = [&](const U t, const U* sy, U* f) {
    const U* sq = sy;
    const U* sv = sy + NQ;
@FIELD@
    for (int i = 0; i < N; ++i) f[i] = frozen ? U{} : f[i];
    for (int j = 0; j < NW; ++j) f[NQ + NV + j] = tracked(j) ? f[NQ + NV + j] : U{};
  };
  auto project = [&](U* x) {
@PROJECT@
  };
  U y[N], fs[N], k[S][N], ys[N], yp[N];
  for (int i = 0; i < NQ; ++i) y[i] = ld(0, i);
  for (int i = 0; i < NV; ++i) y[NQ + i] = ld(1, i);
  for (int j = 0; j < NW; ++j) y[NQ + NV + j] = ld(9, j);
  evaluate(t0, y, fs);
  U dt = dt0;
  dt = dt < dtmax ? dt : dtmax;
  if (has_dtmin) dt = dt > dtmin ? dt : dtmin;
  U tprev = t0, tnext = t0 + dt;
  tnext = tnext < t1 ? tnext : t1;
  U inv_prev = U{} + T(1), inv_prevprev = U{} + T(1);
  I at_dtmin = I{}, code = I{};
  U steps = U{}, accepted = U{}, rejected = U{};
  int64_t saved[W];
  for (int l = 0; l < W; ++l) saved[l] = 0;
  const T* ts = in.x[11];
  const int64_t ts_stride = in.s[11];
  T* out_ys = in.y[4];
  const int64_t ys_width = in.n[4];
  // checkpoints of the reverse sweep (a sixth result): the loop's state every `every` accepted steps
  const bool store = in.y[5] != nullptr;
  constexpr int CK = 3 * N + 7;
  U u[N];  // where fs was evaluated (the last stage's input of the step before: first same as last)
  for (int i = 0; i < N; ++i) u[i] = y[i];
  auto checkpoint = [&](int l) {
    T* row = in.y[5] + (b0 + l) * in.n[5] + int64_t(accepted[l]) / every * CK;
    for (int i = 0; i < N; ++i) row[i] = y[i][l], row[N + i] = fs[i][l], row[2 * N + i] = u[i][l];
    row[3 * N] = tprev[l], row[3 * N + 1] = tnext[l], row[3 * N + 2] = inv_prev[l], row[3 * N + 3] = inv_prevprev[l];
    row[3 * N + 4] = at_dtmin[l] != 0, row[3 * N + 5] = steps[l], row[3 * N + 6] = T(saved[l]);
  };
  if (store)
    for (int l = 0; l < n; ++l) checkpoint(l);
  for (;;) {
    const I active = (tprev < t1) & (steps < max_steps) & (code == 0);
    bool any = false;
    for (int l = 0; l < W; ++l) any |= active[l] != 0;
    if (!any) break;
@ATTEMPT@
    const I moved = active & keep;
    // the saves in this step, by its dense output: y₀ + h Σᵢ Bᵢ(θ) fᵢ (diffrax's interpolant)
    for (int l = 0; l < n; ++l) {
      if (!moved[l]) continue;
      const T* row = ts + (b0 + l) * ts_stride;
      while (saved[l] < n_ts && row[saved[l]] <= tnext[l]) {
        const T span = tnext[l] - tprev[l];
        const T theta = span == T(0) ? T(0) : (row[saved[l]] - tprev[l]) / span;
        T b[S];
        for (int s = 0; s < S; ++s) {
          T acc = P[s][D - 1];
          for (int p = D - 2; p >= 0; --p) acc = acc * theta + P[s][p];
          b[s] = acc;
        }
        T* dst = out_ys + (b0 + l) * ys_width + saved[l] * N;
        for (int i = 0; i < N; ++i) {
          T acc = T(0);
          for (int s = 0; s < S; ++s) acc += b[s] * (k[s][i][l] * h[l]);
          dst[i] = y[i][l] + acc;
        }
        ++saved[l];
      }
    }
    advance<N>(active, moved, y, u, fs, yp, ys, k[S - 1], tprev, tp, tnext, tn, inv_prev, inv_new, inv_prevprev, prev_new,
               at_dtmin, at_new, code, code_new, steps, accepted);
    rejected = (active & (keep == 0)) ? rejected + T(1) : rejected;
    if (store)
      for (int l = 0; l < n; ++l)
        if (moved[l] && int64_t(accepted[l]) % every == 0 && tprev[l] < t1[l]) checkpoint(l);
  }
  for (int i = 0; i < NQ; ++i) st(0, i, y[i]);
  for (int i = 0; i < NV; ++i) st(1, i, y[NQ + i]);
  for (int j = 0; j < NW; ++j) st(2, j, y[NQ + NV + j]);
  U nsaved;
  for (int l = 0; l < W; ++l) nsaved[l] = T(saved[l < n ? l : 0]);
  st(3, 0, tprev);
  st(3, 1, steps);
  st(3, 2, accepted);
  st(3, 3, rejected);
  st(3, 4, __builtin_convertvector(code, V));
  st(3, 5, nsaved);
}

extern "C" void jaxbody_range(const Inputs* in, int64_t b0, int64_t b1) {
  for (int64_t b = b0; b < b1; b += W) adaptive_block(*in, b, b1 - b < W ? int(b1 - b) : W);
}
