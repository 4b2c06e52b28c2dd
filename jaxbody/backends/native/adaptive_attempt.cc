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
      evaluate(ys, k[s]);
    }
    for (int i = 0; i < N; ++i) yp[i] = ys[i];
    project(yp);
    U total = U{};
    I nan_q = I{}, nan_v = I{}, finite = (U{} + T(1)) == T(1);
    for (int i = 0; i < N; ++i) {
      finite &= (yp[i] - yp[i]) == T(0);
      if (i < NQ) nan_q |= yp[i] != yp[i];
      else if (i < NQ + NV) nan_v |= yp[i] != yp[i];
    }
    for (int i = 0; i < N; ++i) {
      if (i == N - 1 && !has_work) break;
      U e = U{};
      for (int j = 0; j < S; ++j) e += E[j] * (k[j][i] * h);  // diffrax: the weights on h·fⱼ
      e = (e != e) ? U{} + T(INFINITY) : e;  // diffrax: a NaN error estimate is infinite
      const I nan = i < NQ ? nan_q : (i < NQ + NV ? nan_v : (yp[i] != yp[i]));
      const U cand = nan ? y[i] : yp[i];
      const U ay = vabs(y[i]), ac = vabs(cand);
      const U r = e / (atol + (ay > ac ? ay : ac) * rtol);
      total += r * r;
    }
    const U scaled = vsqrt(total) / std::sqrt(T(count));
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
