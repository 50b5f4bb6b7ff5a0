/* A plain C loop of the docs/MODEL.md plant in the configuration of the `seed` preset, the yardstick of
 * bench/bench_endurance.py's whole-process simulate figure (issue 13). It is what `hdrig simulate
 * --model seed --input sine:amp=A,freq=F --dt DT --rate RATE` integrates, written the obvious way:
 * voltage drive evaluated per step, flexible linear spring with the kinematic error, the article's
 * motor law (quadratic + Fourier Coulomb level, k_v branch, static factor) and a Coulomb-viscous load,
 * both under Karnopp stick-slip, semi-implicit Euler. Every `decim`-th step a row of the state is
 * written to the output file, as the Python process writes its run file.
 *
 * Usage: seed_loop PARAMS.bin N_HARMONICS AMP_V FREQ_HZ DT_S STEPS DECIM OUT.bin
 * PARAMS.bin holds model.kernel's float parameter vector (float64, indexed as model.registry.P says), so
 * both loops read the same numbers. Built by the bench with gcc -O2 -march=native -lm.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>

/* The slots (J_M, S3, A0, B1, ..., N_PARAMS) are model.registry.P's, given on the compiler's command line
 * by the bench (`slot_defines()`: -DJ_M=0 ...), so this file numbers none of them. */
#ifndef N_PARAMS
#error "build with the slot defines of model.registry.P (bench/bench_simulator.py: slot_defines())"
#endif

static double sgn(double x) { return x > 0.0 ? 1.0 : (x < 0.0 ? -1.0 : 0.0); }

/* Breaking away in `direction` from omega inside the band, over `span`: the static level until the
 * speed reaches the band's edge (located inside the span), the moving law after it. *left: it did. */
static double breakaway(double omega, double psi, double direction, double limit, double level,
                        double viscous, double inertia, double span, double band, int *left) {
    double next = omega + span * (psi - direction * limit) / inertia;
    double speed = direction * omega, speed_next = direction * next;
    *left = speed_next >= band;
    if (!*left) return next;
    double to_edge = span * (band - speed) / (speed_next - speed);
    double at_edge = omega + to_edge * (psi - direction * limit) / inertia;
    double f = direction * level + viscous * at_edge;
    return at_edge + (span - to_edge) * (psi - f) / inertia;
}

/* One Karnopp velocity update, events located inside the step as model/kernel.py's `_karnopp` does;
 * returns the new velocity, the friction applied in *friction. */
static double karnopp(double omega, double psi, double moving, double stat, double viscous,
                      double inertia, double dt, double band, double *friction) {
    double start = omega, span = dt;
    if (fabs(omega) >= band) {
        double direction = sgn(omega);
        double f = direction * (moving > 0.0 ? moving : 0.0) + viscous * omega;
        double next = omega + dt * (psi - f) / inertia;
        if (next * omega >= 0.0) {
            *friction = f;
            return next;
        }
        start = 0.0; /* a reversal stops at its zero crossing; the stuck rule takes the remainder */
        span = dt * next / (next - omega);
    }
    double direction = sgn(psi);
    double limit = stat > 0.0 ? stat : 0.0;
    if (fabs(psi) <= limit) {
        *friction = psi + inertia * omega / dt;
        return 0.0;
    }
    int left;
    double level = moving > 0.0 ? moving : 0.0;
    double next = breakaway(start, psi, direction, limit, level, viscous, inertia, span, band, &left);
    *friction = (span == dt && !left) ? direction * limit : psi - inertia * (next - omega) / dt;
    return next;
}

int main(int argc, char **argv) {
    if (argc != 9) {
        fprintf(stderr, "usage: %s PARAMS.bin N_HARMONICS AMP_V FREQ_HZ DT_S STEPS DECIM OUT.bin\n", argv[0]);
        return 2;
    }
    double p[N_PARAMS];
    FILE *pf = fopen(argv[1], "rb");
    if (!pf || fread(p, sizeof(double), N_PARAMS, pf) != N_PARAMS) {
        fprintf(stderr, "%s: cannot read %d parameters\n", argv[1], N_PARAMS);
        return 2;
    }
    fclose(pf);
    int harmonics = atoi(argv[2]);
    double amp = atof(argv[3]), freq = atof(argv[4]), dt = atof(argv[5]);
    long steps = atol(argv[6]), decim = atol(argv[7]);
    FILE *out = fopen(argv[8], "wb");
    if (!out) {
        fprintf(stderr, "%s: cannot write\n", argv[8]);
        return 2;
    }
    double r = p[R_GEAR], theta_m = 0.0, omega_m = 0.0, theta_l = 0.0, omega_l = 0.0;
    theta_l = r * theta_m + p[KE_A] * sin(p[KE_K] * theta_m + p[KE_PHI]);
    double row[6];
    for (long i = 0; i < steps; i++) {
        double time_s = i * dt;
        double u = amp * sin(2.0 * M_PI * freq * time_s);
        double i_a = (u - p[K_B] * omega_m) / p[R_ARM];
        double torque_m = p[K_M] * i_a;
        double theta_err = p[KE_A] * sin(p[KE_K] * theta_m + p[KE_PHI]);
        double t_s = p[K_S] * (r * theta_m + theta_err - theta_l);
        /* C(θ) and the Fourier ripple P(θ), harmonics by the angle-addition recurrence. */
        double c = (p[S1] * theta_m + p[S2]) * theta_m + p[S3];
        double periodic = 0.5 * p[A0];
        double c1 = cos(theta_m), s1 = sin(theta_m), cn = c1, sn = s1;
        for (int n = 1; n <= harmonics; n++) {
            periodic += p[A0 + n] * cn + p[B1 + n - 1] * sn;
            double cn_next = cn * c1 - sn * s1;
            sn = sn * c1 + cn * s1;
            cn = cn_next;
        }
        double moving_m = c * (1.0 + p[K_V] * (fabs(omega_m) - p[V_C])) + periodic;
        double static_m = p[STATIC_FACTOR] * (c * (1.0 - p[K_V] * p[V_C]) + periodic);
        double f_m, f_l;
        double new_omega_m = karnopp(omega_m, torque_m - r * t_s, moving_m, static_m, p[B_M], p[J_M],
                                     dt, p[OMEGA_STICK_M], &f_m);
        double new_omega_l = karnopp(omega_l, t_s, p[F_CL], p[F_SL], p[B_L], p[J_L], dt,
                                     p[OMEGA_STICK_L], &f_l);
        if (i % decim == 0) {
            row[0] = time_s; row[1] = u; row[2] = theta_m; row[3] = omega_m; row[4] = theta_l;
            row[5] = omega_l;
            fwrite(row, sizeof(double), 6, out);
        }
        omega_m = new_omega_m;
        theta_m += dt * omega_m;
        omega_l = new_omega_l;
        theta_l += dt * omega_l;
    }
    row[0] = steps * dt; row[1] = 0.0; row[2] = theta_m; row[3] = omega_m; row[4] = theta_l;
    row[5] = omega_l;
    fwrite(row, sizeof(double), 6, out); /* the final state, for the bench's agreement check */
    fclose(out);
    return 0;
}
