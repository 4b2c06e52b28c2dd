
#include <memory>
static void vjp_block(const Inputs& in, int64_t b0, int n) {
@ACCESS@
@INVARIANT@
  constexpr int NS = @NQ@ + @NV@;
  U qc[@NQ@], vc[@NV@], qn[@NQ@], vn[@NV@], aq[@NQ@], av[@NV@], rq[@NQ@], rv[@NV@];
  const U t0 = ld(10, 0), t1 = ld(10, 1), steps = ld(10, 2), t1_floor = ld(10, 3);
  const I frozen = ld(10, 6) != T(0);
  const int64_t every = int64_t(ld(10, 7)[0]);
  const U taken = ld(12, 1);
  for (int i = 0; i < @NQ@; ++i) aq[i] = ld(13, i);
  for (int i = 0; i < @NV@; ++i) av[i] = ld(14, i);
  U aw[@NW@];
  for (int j = 0; j < @NW@; ++j) aw[j] = ld(15, j);
  int64_t total = 0;
  for (int l = 0; l < n; ++l) total = int64_t(taken[l]) > total ? int64_t(taken[l]) : total;
  constexpr int KEPT = NS + 3;  // a kept step: its state, length and times
  std::unique_ptr<V[]> kept(new V[every * KEPT]);
  for (int64_t seg = (total - 1) / every; seg >= 0 && total > 0; --seg) {
    const int64_t first = seg * every, end = first + every < total ? first + every : total;
    const int64_t at = seg * (NS + 2);
    for (int i = 0; i < @NQ@; ++i) qc[i] = ld(11, at + i);
    for (int i = 0; i < @NV@; ++i) vc[i] = ld(11, at + @NQ@ + i);
    U tprev = ld(11, at + NS), tnext = ld(11, at + NS + 1);
    for (int64_t r = first; r < end; ++r) {
      V* row = &kept[(r - first) * KEPT];
      const U h = tnext - tprev;
      for (int i = 0; i < @NQ@; ++i) row[i] = qc[i];
      for (int i = 0; i < @NV@; ++i) row[@NQ@ + i] = vc[i];
      row[NS] = h;
      row[NS + 1] = tprev;
      row[NS + 2] = tnext;
      if (r + 1 == end) break;
      {
@STEP@
      }
      for (int i = 0; i < @NQ@; ++i) qc[i] = qn[i];
      for (int i = 0; i < @NV@; ++i) vc[i] = vn[i];
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
      const I active = ((U{} + T(r)) < taken) & (frozen == 0);
      {
        const V* bq = row;
        const V* bv = row + @NQ@;
        const U h = row[NS], tprev = row[NS + 1], tnext = row[NS + 2];
@BODY@
      }
      for (int i = 0; i < @NQ@; ++i) aq[i] = active ? rq[i] : aq[i];
      for (int i = 0; i < @NV@; ++i) av[i] = active ? rv[i] : av[i];
    }
  }
  for (int i = 0; i < @NQ@; ++i) st(0, i, aq[i]);
  for (int i = 0; i < @NV@; ++i) st(1, i, av[i]);
}

extern "C" void jaxbody_range(const Inputs* in, int64_t b0, int64_t b1) {
  for (int64_t b = b0; b < b1; b += W) vjp_block(*in, b, b1 - b < W ? int(b1 - b) : W);
}
