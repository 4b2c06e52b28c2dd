// What the adaptive solve (adaptive_block.cc) and its reverse sweep's replay
// (adaptive_vjp_block.cc) share: the helpers below, at file scope, then, after the marker line,
// one attempted step, pasted into both loops, so that both take the same steps.
static inline V vabs(V x) { return x < T(0) ? -x : x; }
static inline V vpow(V x, T p) {
  if (p == T(0)) return V{} + T(1);  // diffrax leaves a zero coefficient's factor out
  V r;
  for (int l = 0; l < W; ++l) r[l] = jb_pow(x[l], p);
  return r;
}

// the time of a stage of node c in a step from tp to tn of length h: diffrax's t0 + c (t1 - t0),
// and t1 itself for c = 1
static inline V stage_time(T c, V tp, V tn, V h) { return c == T(1) ? tn : tp + c * h; }

// the loop's state after an attempt: a lane whose step was accepted (moved) takes its solution
// yp, where its carried derivative was evaluated (ys, the last stage's input) and that
// derivative (last); every active lane takes the controller's next times, error history, dtmin
// flag, result code and step count. Out of line: g++ 12 at -O2 miscompiled it inlined into the
// one-lane (single-state) build, whose solves then rejected every step; one call per attempt
// costs nothing beside its field evaluations
template <int N>
__attribute__((noinline)) static void advance(I active, I moved, V* y, V* u, V* fs, const V* yp, const V* ys, const V* last, V& tprev,
                           V tp, V& tnext, V tn, V& inv_prev, V inv_new, V& inv_prevprev, V prev_new, I& at_dtmin,
                           I at_new, I& code, I code_new, V& steps, V& accepted) {
  for (int i = 0; i < N; ++i) {
    y[i] = moved ? yp[i] : y[i];
    u[i] = moved ? ys[i] : u[i];
    fs[i] = moved ? last[i] : fs[i];
  }
  tprev = active ? tp : tprev;
  tnext = active ? tn : tnext;
  inv_prev = active ? inv_new : inv_prev;
  inv_prevprev = active ? prev_new : inv_prevprev;
  at_dtmin = active ? at_new : at_dtmin;
  code = active ? code_new : code;
  steps = active ? steps + T(1) : steps;
  accepted = moved ? accepted + T(1) : accepted;
}
//@@ATTEMPT
    // one attempted step of every active lane from (tprev, y) to tnext: the stages (the first
    // is the carried derivative fs: first same as last), the solution (the last stage's input),
    // the embedded error estimate, the quaternions renormalised, and diffrax's PIDController
    // with its rounding of the next step to t1
    const U h = tnext - tprev;
    for (int i = 0; i < N; ++i) k[0][i] = fs[i];
    for (int s = 1; s < S; ++s) {
      for (int i = 0; i < N; ++i) {
        U acc = U{};
        for (int j = 0; j < s; ++j) acc += A[s][j] * k[j][i];
        ys[i] = y[i] + acc * h;
      }
      evaluate(stage_time(C[s], tprev, tnext, h), ys, k[s]);
    }
    for (int i = 0; i < N; ++i) yp[i] = ys[i];
    project(yp);
    U total = U{};
    I nan_q = I{}, nan_v = I{}, nan_w = I{}, finite = (U{} + T(1)) == T(1);
    for (int i = 0; i < N; ++i) {
      finite &= (yp[i] - yp[i]) == T(0);
      if (i < NQ) nan_q |= yp[i] != yp[i];
      else if (i < NQ + NV) nan_v |= yp[i] != yp[i];
      else nan_w |= yp[i] != yp[i];
    }
    for (int i = 0; i < N; ++i) {
      if (i >= NQ + NV && !tracked(i - NQ - NV)) continue;  // a work the solve does not carry
      U e = U{};
      for (int j = 0; j < S; ++j) e += E[j] * (k[j][i] * h);  // diffrax: the weights on h·fⱼ
      e = (e != e) ? U{} + T(INFINITY) : e;  // diffrax: a NaN error estimate is infinite
      const I nan = i < NQ ? nan_q : (i < NQ + NV ? nan_v : nan_w);  // diffrax: per leaf of (q, v, w)
      const U cand = nan ? y[i] : yp[i];
      const U ay = vabs(y[i]), ac = vabs(cand);
      const U r = e / (atol + (ay > ac ? ay : ac) * rtol);
      total += r * r;
    }
    const U scaled = vsqrt(total) / jb_sqrt(T(count));
    I keep = scaled < T(1);
    if (has_dtmin) keep |= at_dtmin;
    U inv = T(1) / scaled;
    U factor = safety * vpow(inv, c1) * vpow(inv_prev, c2) * vpow(inv_prevprev, c3);
    const U fmin = keep ? U{} + T(1) : U{} + factormin;
    const U fmax = keep ? U{} + factormax : U{} + safety;
    factor = (factor != factor) ? factor : (factor > fmin ? factor : fmin);
    factor = (factor != factor) ? factor : (factor < fmax ? factor : fmax);
    U dt = h * factor;
    inv = ((inv == T(0)) | (vabs(inv) == T(INFINITY))) ? U{} + T(1) : inv;
    dt = dt < dtmax ? dt : dtmax;
    I at_new = at_dtmin;
    I dtmin_failed = I{};
    if (has_dtmin) {
      if (!force_dtmin) dtmin_failed = dt < dtmin;
      dt = (at_dtmin & (factor == T(1))) ? dtmin : dt;
      at_new = dt <= dtmin;
      dt = dt > dtmin ? dt : dtmin;
    }
    const U next_t0 = keep ? tnext : tprev;
    const U next_t1 = next_t0 + dt;
    const U inv_new = keep ? inv : inv_prev;
    const U prev_new = keep ? inv_prev : inv_prevprev;
    const U tp = next_t0 < t1 ? next_t0 : t1;
    const U tclip = keep ? t1 : tp + T(0.5) * (t1 - tp);
    const U tn = next_t1 > t1_floor ? tclip : next_t1;
    // diffrax's order of results: the solver's (a kept step that is not finite), then the controller's
    I code_new = code;
    code_new = (code_new == 0) & keep & (finite == 0) ? I{} + 1 : code_new;
    code_new = (code_new == 0) & dtmin_failed ? I{} + 2 : code_new;
