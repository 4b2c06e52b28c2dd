@HERMITE@
// The saves in one step [tprev, tnext] of a block (every pending time up to tnext, as diffrax's
// loop saves them) by its dense output: diffrax's cubic Hermite interpolant from the step's end
// states (y0 = (qc, vc, wc), y1 = (qu, vn, wn)) and its first and last stage increments,
// y0 + θ (k1 + θ (b + θ a)) at θ = (t − tprev) / h, for every lane with a pending save at once,
// until none has one; a frozen lane saves its state (as its field is zero). `saved`: each lane's
// saves so far, `next`: its next save time (inf: none left). Not inlined: the step's loop keeps
// its registers for the step, which calls this only when a lane has a save due.
static __attribute__((noinline)) void save_step(const V* qc, const V* vc, const V* wc, const V* qu, const V* vn,
                                                const V* wn, const V* k1, const V* k4, V tprev, V tnext, I active,
                                                I frozen, const T* ts, int64_t ts_stride, int64_t n_ts, T* out,
                                                int64_t width, int64_t b0, int n, int64_t* saved, V& next) {
  constexpr int NQ = @NQ@, NV = @NV@, NW = @NW@, N = NQ + NV + NW;
  for (;;) {
    const I pending = active & (next <= tnext);
    bool any = false;
    for (int l = 0; l < n; ++l) any |= pending[l] != 0;
    if (!any) break;
    const V theta = hermite_theta(tprev, next, tnext);
    V y[N];
    for (int i = 0; i < NQ; ++i) y[i] = frozen ? qc[i] : hermite(qc[i], qu[i], k1[i], k4[i], theta);
    for (int i = 0; i < NV; ++i) y[NQ + i] = frozen ? vc[i] : hermite(vc[i], vn[i], k1[NQ + i], k4[NQ + i], theta);
    for (int j = 0; j < NW; ++j) {
      const int i = NQ + NV + j;
      y[i] = frozen ? wc[j] : hermite(wc[j], wn[j], k1[i], k4[i], theta);
    }
    for (int l = 0; l < n; ++l) {
      if (!pending[l]) continue;
      T* dst = out + (b0 + l) * width + saved[l] * N;
      for (int i = 0; i < N; ++i) dst[i] = y[i][l];
      ++saved[l];
      next[l] = saved[l] < n_ts ? ts[(b0 + l) * ts_stride + saved[l]] : T(INFINITY);
    }
  }
}

static void run_block(const Inputs& in, int64_t b0, int n) {
@ACCESS@
@INVARIANT@
  constexpr int NQ = @NQ@, NV = @NV@, NW = @NW@, N = NQ + NV + NW;
  U qc[NQ], vc[NV], qn[NQ], vn[NV];
  for (int i = 0; i < NQ; ++i) qc[i] = ld(0, i);
  for (int i = 0; i < NV; ++i) vc[i] = ld(1, i);
  U wc[NW], dw[NW], wn[NW];
  for (int j = 0; j < NW; ++j) wc[j] = ld(9, j);
  // the step's dense output: its first and last stage increments of (q, v, w), and q1 before
  // the quaternions' renormalisation (what diffrax's interpolant of the step reads)
  U k1[N], k4[N], qu[NQ];
  const U t0 = ld(10, 0), t1 = ld(10, 1), steps = ld(10, 2), t1_floor = ld(10, 3), limit = ld(10, 4), dt0 = ld(10, 5);
  const I frozen = ld(10, 6) != T(0);
  const int64_t n_ts = int64_t(ld(10, 8)[0]);
  // the save times (operand 11) and the saved states (result 4: n_ts rows of N)
  const T* ts = in.x[11];
  const int64_t ts_stride = in.s[11];
  T* out_ys = in.y[4];
  const int64_t ys_width = in.n[4];
  int64_t saved[W];
  U next_save;  // each lane's next save time (inf: none)
  for (int l = 0; l < W; ++l) saved[l] = 0, next_save[l] = n_ts > 0 && l < n ? ts[(b0 + l) * ts_stride] : T(INFINITY);
  U tprev = t0, tnext = t0 + dt0;
  tnext = tnext < t1 ? tnext : t1;
  U count = U{};
  I failed = I{};
  // checkpoints (a sixth result): every `every` steps
  const bool store = in.y[5] != nullptr;
  const int64_t every = store ? int64_t(ld(10, 7)[0]) : 1;
  int64_t it = 0;
  for (;;) {
    const I active = (tprev < t1) & (count < limit) & (failed == 0);
    bool any = false;
    for (int l = 0; l < W; ++l) any |= active[l] != 0;
    if (!any) break;
    if (store && it % every == 0) {
      // a checkpoint: the state at the start of this step, its times and the saves made so far
      // (the reverse sweep recomputes the steps from here); active lanes all have taken `it` steps
      const int64_t at = (it / every) * (NQ + NV + 3);
      for (int i = 0; i < NQ; ++i) st(5, at + i, qc[i]);
      for (int i = 0; i < NV; ++i) st(5, at + NQ + i, vc[i]);
      st(5, at + NQ + NV, tprev);
      st(5, at + NQ + NV + 1, tnext);
      U made;
      for (int l = 0; l < W; ++l) made[l] = T(saved[l]);
      st(5, at + NQ + NV + 2, made);
    }
    ++it;
    const U h = tnext - tprev;
    {
@BODY@
    }
    I finite = (U{} + T(1)) == T(1);
    for (int j = 0; j < NW; ++j) wn[j] = wc[j] + dw[j], finite &= (wn[j] - wn[j]) == T(0);  // false for inf and NaN
    for (int i = 0; i < NQ; ++i) finite &= (qn[i] - qn[i]) == T(0);
    for (int i = 0; i < NV; ++i) finite &= (vn[i] - vn[i]) == T(0);
    finite |= frozen;
    // the saves in this step (save_step), where a lane has one due
    if (n_ts > 0) {
      const I due = active & (next_save <= tnext);
      bool any_due = false;
      for (int l = 0; l < n; ++l) any_due |= due[l] != 0;
      if (any_due)
        save_step(qc, vc, wc, qu, vn, wn, k1, k4, tprev, tnext, active, frozen, ts, ts_stride, n_ts, out_ys, ys_width,
                  b0, n, saved, next_save);
    }
    // a lane that is done keeps its state, and so does a frozen one (its time runs on)
    const I moving = active & (frozen == 0);
    for (int i = 0; i < NQ; ++i) qc[i] = moving ? qn[i] : qc[i];
    for (int i = 0; i < NV; ++i) vc[i] = moving ? vn[i] : vc[i];
    for (int j = 0; j < NW; ++j) wc[j] = moving ? wn[j] : wc[j];
    count = active ? count + T(1) : count;
    failed |= active & (finite == 0);
    const U next = count + T(1);
    U tn = t0 + (t1 - t0) * (next / steps);
    tn = next == steps ? t1 : tn;
    tn = tn > t1_floor ? t1 : tn;
    const U tp = tnext < t1 ? tnext : t1;
    tprev = active ? tp : tprev;
    tnext = active ? tn : tnext;
  }
  for (int i = 0; i < NQ; ++i) st(0, i, qc[i]);
  for (int i = 0; i < NV; ++i) st(1, i, vc[i]);
  for (int j = 0; j < NW; ++j) st(2, j, wc[j]);
  // the status row of the whole solves (jaxbody.backends.native.solve.STATUS): every step
  // accepted, none rejected; the code 1 for a step that was not finite
  U made;
  for (int l = 0; l < W; ++l) made[l] = T(saved[l < n ? l : 0]);
  st(3, 0, tprev);
  st(3, 1, count);
  st(3, 2, count);
  st(3, 3, U{});
  st(3, 4, failed != 0 ? U{} + T(1) : U{});
  st(3, 5, made);
}

extern "C" void jaxbody_range(const Inputs* in, int64_t b0, int64_t b1) {
  for (int64_t b = b0; b < b1; b += W) run_block(*in, b, b1 - b < W ? int(b1 - b) : W);
}
