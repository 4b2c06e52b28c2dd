  typedef V U;
  int64_t idx[W];
  for (int l = 0; l < W; ++l) idx[l] = b0 + (l < n ? l : n - 1);
  auto ld = [&](int k, int i) {
    const T* x = in.x[k];
    const int64_t s = in.s[k];
    // an operand shared by all states (the model under a vmap over states), or a block of
    // one state: one load broadcast to every lane; else one load per lane
    if (s == 0) return U{} + x[i];
    if (n == 1) return U{} + x[b0 * s + i];
#if JB_GATHER
    return gather_rows(x + b0 * s + i, s, n);
#else
    U r;
    for (int l = 0; l < W; ++l) r[l] = x[idx[l] * s + i];
    return r;
#endif
  };
  auto st = [&](int j, int i, U x) {
#if JB_GATHER
    scatter_rows(in.y[j] + b0 * in.n[j] + i, in.n[j], n, x);
#else
    for (int l = 0; l < n; ++l) in.y[j][(b0 + l) * in.n[j] + i] = x[l];
#endif
  };
  auto sc = [n](U x, U& s, U& c) { vsincos(x, s, c, n); };