// Native Ceres on a BAL file: the comparison solver of benchmarks/bench_ba.py.
//
//   ceres_bal FILE ITERATIONS THREADS   ->  one JSON line on stdout
//
// Residual r = f d(|p|^2) p - obs with P = R(w) X + t, p = -P_xy / P_z, d = 1 + k1 |p|^2 +
// k2 |p|^4 (the BAL model of mslam_ref.ba.cameras), automatic derivatives, SPARSE_SCHUR over
// SuiteSparse, Levenberg-Marquardt, exactly ITERATIONS iterations (all tolerances 0). The time
// is the solver's own wall time (Solver::Summary::total_time_in_seconds).
#include <ceres/ceres.h>
#include <ceres/rotation.h>

#include <cstdio>
#include <vector>

struct BalResidual {
  BalResidual(double u, double v) : u(u), v(v) {}
  template <typename T>
  bool operator()(const T* cam, const T* X, T* r) const {
    T P[3];
    ceres::AngleAxisRotatePoint(cam, X, P);
    for (int i = 0; i < 3; ++i) P[i] += cam[3 + i];
    const T px = -P[0] / P[2], py = -P[1] / P[2];
    const T r2 = px * px + py * py;
    const T d = T(1.0) + r2 * (cam[7] + cam[8] * r2);
    r[0] = cam[6] * d * px - u;
    r[1] = cam[6] * d * py - v;
    return true;
  }
  double u, v;
};

int main(int argc, char** argv) {
  if (argc != 4) {
    std::fprintf(stderr, "usage: ceres_bal FILE ITERATIONS THREADS\n");
    return 2;
  }
  FILE* f = std::fopen(argv[1], "r");
  if (!f) {
    std::fprintf(stderr, "%s: cannot open\n", argv[1]);
    return 2;
  }
  int M, P, O;
  if (std::fscanf(f, "%d %d %d", &M, &P, &O) != 3) return 2;
  std::vector<int> oc(O), op(O);
  std::vector<double> obs(2 * O), cams(9 * M), pts(3 * P);
  for (int e = 0; e < O; ++e)
    if (std::fscanf(f, "%d %d %lf %lf", &oc[e], &op[e], &obs[2 * e], &obs[2 * e + 1]) != 4) return 2;
  for (auto& x : cams)
    if (std::fscanf(f, "%lf", &x) != 1) return 2;
  for (auto& x : pts)
    if (std::fscanf(f, "%lf", &x) != 1) return 2;
  std::fclose(f);
  ceres::Problem problem;
  for (int e = 0; e < O; ++e) {
    auto* cost = new ceres::AutoDiffCostFunction<BalResidual, 2, 9, 3>(
        new BalResidual(obs[2 * e], obs[2 * e + 1]));
    problem.AddResidualBlock(cost, nullptr, &cams[9 * oc[e]], &pts[3 * op[e]]);
  }
  ceres::Solver::Options opt;
  opt.linear_solver_type = ceres::SPARSE_SCHUR;
  opt.sparse_linear_algebra_library_type = ceres::SUITE_SPARSE;
  opt.max_num_iterations = std::atoi(argv[2]);
  opt.num_threads = std::atoi(argv[3]);
  opt.function_tolerance = 0.0;
  opt.gradient_tolerance = 0.0;
  opt.parameter_tolerance = 0.0;
  ceres::Solver::Summary s;
  ceres::Solve(opt, &problem, &s);
  std::printf(
      "{\"time\": %.6f, \"initial_cost\": %.10g, \"final_cost\": %.10g, \"iterations\": %d, "
      "\"linear_solver\": %.6f, \"residual_jacobian\": %.6f, \"preprocessor\": %.6f}\n",
      s.total_time_in_seconds, s.initial_cost, s.final_cost,
      s.num_successful_steps + s.num_unsuccessful_steps, s.linear_solver_time_in_seconds,
      s.residual_evaluation_time_in_seconds + s.jacobian_evaluation_time_in_seconds,
      s.preprocessor_time_in_seconds);
  return 0;
}
