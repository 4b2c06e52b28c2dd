
// The reverse sweep of a whole adaptive solve (reverse mode with respect to the initial state,
// the accepted steps held: diffrax stops the gradient through the step-size controller too).
// For each segment of `every` accepted steps, last first, the solve is replayed from the
// segment's checkpoint (the same attempts, so the same accepted steps) and every accepted
// step's start is kept; then each kept step is reversed: its stages recomputed, and the
// cotangents carried back through the quaternion renormalisation, the stage combinations and
// the field's generated reverse-mode program. The first stage of a step is the last stage of
// the step before (first same as last): its cotangent goes back to that step's solution
// before renormalisation (`pend`).
@HELPERS@

static void adaptive_vjp_block(const Inputs& in, int64_t b0, int n) {
@ACCESS@
@INVARIANT@
  constexpr int NQ = @NQ@, NV = @NV@, NW = @NW@, N = NQ + NV + NW, S = @S@, D = @D@;
  static const T A[S][S] = @A@;
  static const T E[S] = @E@;
  static const T P[S][D] = @P@;
  static const T C[S] = @C@;
  const U t1 = ld(10, 1), t1_floor = ld(10, 2), max_steps = ld(10, 3);
  const U rtol = ld(10, 5), atol = ld(10, 6), dtmin = ld(10, 10), dtmax = ld(10, 11);
  const T pcoeff = ld(10, 7)[0], icoeff = ld(10, 8)[0], dcoeff = ld(10, 9)[0], order = ld(10, 16)[0];
  const bool force_dtmin = ld(10, 12)[0] != T(0), has_dtmin = ld(10, 20)[0] != T(0);
  // the works the solve carries (bit j: the program's work j, the powers of the field in order)
  const int64_t works = int64_t(ld(10, 18)[0]);
  auto tracked = [works](int j) { return ((works >> j) & 1) != 0; };
  const T factormin = ld(10, 13)[0], factormax = ld(10, 14)[0], safety = ld(10, 15)[0];
  const I frozen = ld(10, 17) != T(0);
  const int64_t every = int64_t(ld(10, 19)[0]), n_ts = int64_t(ld(10, 21)[0]);
  // the save times (operand 16) and the cotangents of the saved states (operand 17)
  const T* ts = in.x[16];
  const int64_t ts_stride = in.s[16];
  const T* ct_saved = in.x[17];
  const int64_t ct_stride = in.s[17];
  const T c1 = (icoeff + pcoeff + dcoeff) / order, c2 = -(pcoeff + T(2) * dcoeff) / order, c3 = dcoeff / order;
  int count = NQ + NV;
  for (int j = 0; j < NW; ++j) count += tracked(j) ? 1 : 0;
  auto evaluate = [&](const U t, const U* sy, U* f) {
    const U* sq = sy;
    const U* sv = sy + NQ;
@FIELD@
    for (int i = 0; i < N; ++i) f[i] = frozen ? U{} : f[i];
    for (int j = 0; j < NW; ++j) f[NQ + NV + j] = tracked(j) ? f[NQ + NV + j] : U{};
  };
  // cotangents of (q, v) at sy for cotangents lf of the field (q̇, a, P)
  auto evaluate_vjp = [&](const U t, const U* sy, const U* lf, U* r) {
    const U* sq = sy;
    const U* sv = sy + NQ;
@FIELD_VJP@
    for (int i = 0; i < NQ + NV; ++i) r[i] = frozen ? U{} : r[i];
  };
  auto project = [&](U* x) {
@PROJECT@
  };
  // cotangent of the state before renormalisation for a cotangent of the state after it
  auto project_vjp = [&](const U* x, U* lam) {
@PROJECT_VJP@
  };
  const U taken = ld(12, 2);  // accepted steps of each lane
  U lam[N], pend[N];
  for (int i = 0; i < NQ; ++i) lam[i] = ld(13, i);
  for (int i = 0; i < NV; ++i) lam[NQ + i] = ld(14, i);
  for (int j = 0; j < NW; ++j) lam[NQ + NV + j] = ld(15, j);
  for (int i = 0; i < N; ++i) pend[i] = U{};
  int64_t total = 0;
  for (int l = 0; l < n; ++l) total = int64_t(taken[l]) > total ? int64_t(taken[l]) : total;
  constexpr int CK = 3 * N + 7, KEPT = 3 * N + 5;
  Owned<V> kept(every * KEPT);
  U y[N], fs[N], u[N], k[S][N], ys[N], yp[N], Y[S][N], lk[S][N], ly[N], r[N];
  for (int64_t seg = (total - 1) / every; seg >= 0 && total > 0; --seg) {
    const int64_t first = seg * every;
    // the segment's checkpoint, lane by lane (a lane with fewer steps reads its first)
    U tprev, tnext, inv_prev, inv_prevprev, steps, accepted = U{} + T(first);
    I at_dtmin;
    for (int l = 0; l < W; ++l) {
      const int ll = l < n ? l : n - 1;
      const int64_t slot = first < int64_t(taken[ll]) ? seg : 0;
      const T* row = in.x[11] + (b0 + ll) * in.s[11] + slot * CK;
      for (int i = 0; i < N; ++i) y[i][l] = row[i], fs[i][l] = row[N + i], u[i][l] = row[2 * N + i];
      tprev[l] = row[3 * N], tnext[l] = row[3 * N + 1], inv_prev[l] = row[3 * N + 2], inv_prevprev[l] = row[3 * N + 3];
      at_dtmin[l] = row[3 * N + 4] != T(0) ? -1 : 0;
      steps[l] = row[3 * N + 5];
    }
    int64_t saved[W];
    for (int l = 0; l < W; ++l) {
      const int ll = l < n ? l : n - 1;
      const int64_t slot = first < int64_t(taken[ll]) ? seg : 0;
      saved[l] = int64_t(in.x[11][(b0 + ll) * in.s[11] + slot * CK + 3 * N + 6]);
    }
    I code = I{};
    U end = taken < T(first + every) ? taken : U{} + T(first + every);
    // replay: keep each accepted step's start (y, u, fs) and length
    for (;;) {
      const I active = (accepted < end) & (tprev < t1) & (steps < max_steps) & (code == 0);
      bool any = false;
      for (int l = 0; l < W; ++l) any |= active[l] != 0;
      if (!any) break;
@ATTEMPT@
      const I moved = active & keep;
      for (int l = 0; l < W; ++l) {
        if (!moved[l]) continue;
        V* row = &kept[(int64_t(accepted[l]) - first) * KEPT];
        for (int i = 0; i < N; ++i) row[i][l] = y[i][l], row[N + i][l] = u[i][l], row[2 * N + i][l] = fs[i][l];
        row[3 * N][l] = h[l];
        row[3 * N + 1][l] = tprev[l];
        row[3 * N + 4][l] = tnext[l];
        // the saves this step made (as the solve makes them)
        const int ll = l < n ? l : n - 1;
        const T* trow = ts + (b0 + ll) * ts_stride;
        row[3 * N + 2][l] = T(saved[l]);
        while (saved[l] < n_ts && trow[saved[l]] <= tnext[l]) ++saved[l];
        row[3 * N + 3][l] = T(saved[l]);
      }
      advance<N>(active, moved, y, u, fs, yp, ys, k[S - 1], tprev, tp, tnext, tn, inv_prev, inv_new, inv_prevprev, prev_new,
                 at_dtmin, at_new, code, code_new, steps, accepted);
    }
    int64_t last = 0;
    for (int l = 0; l < n; ++l) last = int64_t(end[l]) > last ? int64_t(end[l]) : last;
    for (int64_t rr = last - 1; rr >= first; --rr) {
      const I active = (U{} + T(rr)) < end;
      const V* row = &kept[(rr - first) * KEPT];
      const U h = row[3 * N], tp = row[3 * N + 1], tn = row[3 * N + 4];
      for (int i = 0; i < N; ++i) y[i] = row[i], u[i] = row[N + i], k[0][i] = row[2 * N + i];
      for (int s = 1; s < S; ++s) {
        for (int i = 0; i < N; ++i) {
          U acc = U{};
          for (int j = 0; j < s; ++j) acc += A[s][j] * k[j][i];
          Y[s][i] = y[i] + acc * h;
        }
        evaluate(stage_time(C[s], tp, tn, h), Y[s], k[s]);
      }
      // the solution is the last stage's input, renormalised
      for (int i = 0; i < N; ++i) ly[i] = lam[i];
      project_vjp(Y[S - 1], ly);
      for (int i = 0; i < N; ++i) ly[i] += pend[i];
      U ly0[N];
      for (int i = 0; i < N; ++i) ly0[i] = U{};
      for (int s = 0; s < S; ++s)
        for (int i = 0; i < N; ++i) lk[s][i] = U{};
      // the states saved in this step, y₀ + Σₛ Bₛ(θ) (h fₛ): their cotangents
      bool dense = false;  // a save in this step: the last stage's field enters through the interpolant
      for (int l = 0; l < n; ++l) {
        if (!active[l]) continue;
        dense |= row[3 * N + 3][l] > row[3 * N + 2][l];
        const T* trow = ts + (b0 + l) * ts_stride;
        const T* crow = ct_saved + (b0 + l) * ct_stride;
        const T tp = row[3 * N + 1][l], span = h[l];
        for (int64_t idx = int64_t(row[3 * N + 2][l]); idx < int64_t(row[3 * N + 3][l]); ++idx) {
          const T theta = span == T(0) ? T(0) : (trow[idx] - tp) / span;
          for (int s = 0; s < S; ++s) {
            T acc = P[s][D - 1];
            for (int p = D - 2; p >= 0; --p) acc = acc * theta + P[s][p];
            for (int i = 0; i < N; ++i) lk[s][i][l] += acc * span * crow[idx * N + i];
          }
          for (int i = 0; i < N; ++i) ly0[i][l] += crow[idx * N + i];
        }
      }
      for (int s = S - 1; s >= 1; --s) {
        if (s < S - 1) {
          evaluate_vjp(stage_time(C[s], tp, tn, h), Y[s], lk[s], r);
          for (int i = 0; i < NQ + NV; ++i) ly[i] = r[i];
          for (int i = NQ + NV; i < N; ++i) ly[i] = U{};
        } else if (dense) {
          // the last stage's input is the solution (its cotangent so far) and the field there
          // feeds the saved states
          evaluate_vjp(stage_time(C[s], tp, tn, h), Y[s], lk[s], r);
          for (int i = 0; i < NQ + NV; ++i) ly[i] += r[i];
        }
        // this stage's input: y0 + (Σⱼ aₛⱼ fⱼ) h
        for (int i = 0; i < N; ++i) {
          ly0[i] += ly[i];
          for (int j = 0; j < s; ++j) lk[j][i] += (A[s][j] * ly[i]) * h;
        }
        if (s < S - 1) {
          // the stage's input also carries the cotangent of the work it reads (none: the field
          // does not read w), so ly is complete
        }
      }
      // the first stage was the field at u (the step before's solution before renormalisation)
      evaluate_vjp(tp, u, lk[0], r);
      for (int i = 0; i < N; ++i) {
        const U pn = i < NQ + NV ? r[i] : U{};
        lam[i] = active ? ly0[i] : lam[i];
        pend[i] = active ? pn : pend[i];
      }
    }
  }
  // the first step's first stage was the field at the initial state itself
  for (int i = 0; i < NQ; ++i) st(0, i, lam[i] + pend[i]);
  for (int i = 0; i < NV; ++i) st(1, i, lam[NQ + i] + pend[NQ + i]);
  for (int j = 0; j < NW; ++j) st(2, j, lam[NQ + NV + j]);
}

extern "C" void jaxbody_range(const Inputs* in, int64_t b0, int64_t b1) {
  for (int64_t b = b0; b < b1; b += W) adaptive_vjp_block(*in, b, b1 - b < W ? int(b1 - b) : W);
}
