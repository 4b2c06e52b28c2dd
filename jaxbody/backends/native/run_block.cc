
static void run_block(const Inputs& in, int64_t b0, int n) {
@ACCESS@
@INVARIANT@
  U qc[@NQ@], vc[@NV@], qn[@NQ@], vn[@NV@];
  for (int i = 0; i < @NQ@; ++i) qc[i] = ld(0, i);
  for (int i = 0; i < @NV@; ++i) vc[i] = ld(1, i);
  U wc[@NW@], dw[@NW@], wn[@NW@];
  for (int j = 0; j < @NW@; ++j) wc[j] = ld(9, j);
  const U t0 = ld(10, 0), t1 = ld(10, 1), steps = ld(10, 2), t1_floor = ld(10, 3), limit = ld(10, 4), dt0 = ld(10, 5);
  const I frozen = ld(10, 6) != T(0);
  U tprev = t0, tnext = t0 + dt0;
  tnext = tnext < t1 ? tnext : t1;
  U count = U{};
  I failed = I{};
  // checkpoints (a fifth result): every `every` steps
  const bool store = in.y[4] != nullptr;
  const int64_t every = store ? int64_t(ld(10, 7)[0]) : 1;
  int64_t it = 0;
  for (;;) {
    const I active = (tprev < t1) & (count < limit) & (failed == 0);
    bool any = false;
    for (int l = 0; l < W; ++l) any |= active[l] != 0;
    if (!any) break;
    if (store && it % every == 0) {
      // a checkpoint: the state at the start of this step and its times (the reverse sweep
      // recomputes the steps from here); active lanes all have taken `it` steps
      const int64_t at = (it / every) * (@NQ@ + @NV@ + 2);
      for (int i = 0; i < @NQ@; ++i) st(4, at + i, qc[i]);
      for (int i = 0; i < @NV@; ++i) st(4, at + @NQ@ + i, vc[i]);
      st(4, at + @NQ@ + @NV@, tprev);
      st(4, at + @NQ@ + @NV@ + 1, tnext);
    }
    ++it;
    const U h = tnext - tprev;
    {
@BODY@
    }
    I finite = (U{} + T(1)) == T(1);
    for (int j = 0; j < @NW@; ++j) wn[j] = wc[j] + dw[j], finite &= (wn[j] - wn[j]) == T(0);  // false for inf and NaN
    for (int i = 0; i < @NQ@; ++i) finite &= (qn[i] - qn[i]) == T(0);
    for (int i = 0; i < @NV@; ++i) finite &= (vn[i] - vn[i]) == T(0);
    finite |= frozen;
    // a lane that is done keeps its state, and so does a frozen one (its time runs on)
    const I moving = active & (frozen == 0);
    for (int i = 0; i < @NQ@; ++i) qc[i] = moving ? qn[i] : qc[i];
    for (int i = 0; i < @NV@; ++i) vc[i] = moving ? vn[i] : vc[i];
    for (int j = 0; j < @NW@; ++j) wc[j] = moving ? wn[j] : wc[j];
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
  for (int i = 0; i < @NQ@; ++i) st(0, i, qc[i]);
  for (int i = 0; i < @NV@; ++i) st(1, i, vc[i]);
  for (int j = 0; j < @NW@; ++j) st(2, j, wc[j]);
  st(3, 0, tprev);
  st(3, 1, count);
  st(3, 2, failed != 0 ? U{} + T(1) : U{});
}

extern "C" void jaxbody_range(const Inputs* in, int64_t b0, int64_t b1) {
  for (int64_t b = b0; b < b1; b += W) run_block(*in, b, b1 - b < W ? int(b1 - b) : W);
}
