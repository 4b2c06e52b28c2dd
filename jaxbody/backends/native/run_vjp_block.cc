@HERMITE@
// The cotangents of the states a kept step saved (`row`: its state, length, times and saves
// [first, end)): y(θ) = h00 y0 + h01 y1 + h10 k1 + h11 k4 puts them onto the step's start (l0),
// end (l1) and stage increments (sk1, sk4); a frozen lane saved its state itself. Not inlined:
// the sweep's loop keeps its registers for the step's reverse-mode program.
static __attribute__((noinline)) void save_cotangents(const V* row, I stepped, I frozen, const T* ts, int64_t ts_stride,
                                                      const T* ct, int64_t ct_stride, int64_t b0, int n, V* l0, V* l1,
                                                      V* sk1, V* sk4) {
  constexpr int NS = @NQ@ + @NV@, N = NS + @NW@;
  for (int i = 0; i < N; ++i) l0[i] = V{}, l1[i] = V{}, sk1[i] = V{}, sk4[i] = V{};
  for (int l = 0; l < n; ++l) {
    if (!stepped[l]) continue;
    const T* trow = ts + (b0 + l) * ts_stride;
    const T* crow = ct + (b0 + l) * ct_stride;
    for (int64_t idx = int64_t(row[NS + 3][l]); idx < int64_t(row[NS + 4][l]); ++idx) {
      T w[4] = {T(1), T(0), T(0), T(0)};
      if (!frozen[l]) hermite_weights(hermite_theta(row[NS + 1][l], trow[idx], row[NS + 2][l]), w);
      for (int i = 0; i < N; ++i) {
        const T c = crow[idx * N + i];
        l0[i][l] += w[0] * c, l1[i][l] += w[1] * c, sk1[i][l] += w[2] * c, sk4[i][l] += w[3] * c;
      }
    }
  }
}

static void vjp_block(const Inputs& in, int64_t b0, int n) {
@ACCESS@
@INVARIANT@
  constexpr int NQ = @NQ@, NV = @NV@, NW = @NW@, NS = NQ + NV, N = NS + NW;
  U qc[NQ], vc[NV], qn[NQ], vn[NV], aq[NQ], av[NV], rq[NQ], rv[NV];
  const U t0 = ld(10, 0), t1 = ld(10, 1), steps = ld(10, 2), t1_floor = ld(10, 3);
  const I frozen = ld(10, 6) != T(0);
  const int64_t every = int64_t(ld(10, 7)[0]), n_ts = int64_t(ld(10, 8)[0]);
  // the save times (operand 16) and the cotangents of the saved states (operand 17)
  const T* ts = in.x[16];
  const int64_t ts_stride = in.s[16];
  const T* ct_saved = in.x[17];
  const int64_t ct_stride = in.s[17];
  const U taken = ld(12, 1);
  for (int i = 0; i < NQ; ++i) aq[i] = ld(13, i);
  for (int i = 0; i < NV; ++i) av[i] = ld(14, i);
  U aw[NW];
  for (int j = 0; j < NW; ++j) aw[j] = ld(15, j);
  // the cotangents the step's reverse-mode program takes: of q1, v1, Δw, and of the dense
  // output's stage increments and q1 before renormalisation (zero in a step without saves)
  U sq[NQ], sv[NV], sw[NW], sk1[N], sk4[N], squ[NQ];
  // the saved states' cotangents on the step's start and end state (y0, y1)
  U l0[N], l1[N];
  for (int i = 0; i < N; ++i) l0[i] = U{}, l1[i] = U{}, sk1[i] = U{}, sk4[i] = U{};
  int64_t total = 0;
  for (int l = 0; l < n; ++l) total = int64_t(taken[l]) > total ? int64_t(taken[l]) : total;
  constexpr int CK = NS + 3;    // a checkpoint: the state, the step's times, the saves made
  constexpr int KEPT = NS + 5;  // a kept step: its state, length, times and its saves [first, end)
  Owned<V> kept(every * KEPT);
  for (int64_t seg = (total - 1) / every; seg >= 0 && total > 0; --seg) {
    const int64_t first = seg * every, end = first + every < total ? first + every : total;
    const int64_t at = seg * CK;
    for (int i = 0; i < NQ; ++i) qc[i] = ld(11, at + i);
    for (int i = 0; i < NV; ++i) vc[i] = ld(11, at + NQ + i);
    U tprev = ld(11, at + NS), tnext = ld(11, at + NS + 1);
    // the saves made before the segment, lane by lane (a lane that did not reach it: none)
    int64_t saved[W];
    {
      const U made = ld(11, at + NS + 2);
      for (int l = 0; l < W; ++l) saved[l] = T(first) < taken[l] ? int64_t(made[l]) : 0;
    }
    for (int64_t r = first; r < end; ++r) {
      V* row = &kept[(r - first) * KEPT];
      const U h = tnext - tprev;
      for (int i = 0; i < NQ; ++i) row[i] = qc[i];
      for (int i = 0; i < NV; ++i) row[NQ + i] = vc[i];
      row[NS] = h;
      row[NS + 1] = tprev;
      row[NS + 2] = tnext;
      // the saves this step made (as the solve makes them)
      for (int l = 0; l < W; ++l) {
        row[NS + 3][l] = T(saved[l]);
        if (l < n && T(r) < taken[l]) {
          const T* trow = ts + (b0 + l) * ts_stride;
          while (saved[l] < n_ts && trow[saved[l]] <= tnext[l]) ++saved[l];
        }
        row[NS + 4][l] = T(saved[l]);
      }
      if (r + 1 == end) break;
      {
@STEP@
      }
      for (int i = 0; i < NQ; ++i) qc[i] = qn[i];
      for (int i = 0; i < NV; ++i) vc[i] = vn[i];
      // the times of the next step, as the forward loop takes them (after r + 1 steps)
      const U next = U{} + T(r + 2);
      U tn = t0 + (t1 - t0) * (next / steps);
      tn = next == steps ? t1 : tn;
      tn = tn > t1_floor ? t1 : tn;
      tprev = tnext < t1 ? tnext : t1;
      tnext = tn;
    }
    for (int64_t r = end - 1; r >= first; --r) {
      const V* row = &kept[(r - first) * KEPT];
      const I stepped = (U{} + T(r)) < taken;
      const I active = stepped & (frozen == 0);
      // the saved states' cotangents (a solve without save times: all zero, as set before the sweep)
      if (n_ts > 0) {
        // filled out of line, copied in: the arrays the step's program reads stay the sweep's own
        V c0[N], c1[N], ck1[N], ck4[N];
        save_cotangents(row, stepped, frozen, ts, ts_stride, ct_saved, ct_stride, b0, n, c0, c1, ck1, ck4);
        for (int i = 0; i < N; ++i) l0[i] = c0[i], l1[i] = c1[i], sk1[i] = ck1[i], sk4[i] = ck4[i];
      }
      // q1 is the renormalised end state; the interpolant reads it before renormalisation
      for (int i = 0; i < NQ; ++i) sq[i] = aq[i], squ[i] = l1[i];
      for (int i = 0; i < NV; ++i) sv[i] = av[i] + l1[NQ + i];
      // w1 = w0 + Δw
      for (int j = 0; j < NW; ++j) sw[j] = aw[j] + l1[NS + j];
      {
        const V* bq = row;
        const V* bv = row + NQ;
        const U h = row[NS], tprev = row[NS + 1], tnext = row[NS + 2];
@BODY@
      }
      for (int i = 0; i < NQ; ++i) aq[i] = (active ? rq[i] : aq[i]) + l0[i];
      for (int i = 0; i < NV; ++i) av[i] = (active ? rv[i] : av[i]) + l0[NQ + i];
      for (int j = 0; j < NW; ++j) aw[j] = aw[j] + l0[NS + j] + l1[NS + j];
    }
  }
  for (int i = 0; i < NQ; ++i) st(0, i, aq[i]);
  for (int i = 0; i < NV; ++i) st(1, i, av[i]);
  for (int j = 0; j < NW; ++j) st(2, j, aw[j]);
}

extern "C" void jaxbody_range(const Inputs* in, int64_t b0, int64_t b1) {
  for (int64_t b = b0; b < b1; b += W) vjp_block(*in, b, b1 - b < W ? int(b1 - b) : W);
}
