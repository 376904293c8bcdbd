// polyfit_bench: what the polynomial compression of fit/polyfit.h chooses and what it costs in
// accuracy, printed as Markdown tables.
//
//   polyfit_bench [seeds]     (default 5 seeds per row)
//
// Table 1: for smooth test functions of the angle over 0..30 deg with seeded Gaussian noise at
// several levels and sample counts, the degree cross-validation chose (over the seeds), the
// number of pieces, and the held-out error: RMS against the noise-free function on 1000 angles
// that are not samples, for the chosen fit and for fixed degrees 1..8 (mean over seeds).
// Table 2: the condition number of the degree-8 least-squares design matrix in monomials of the
// raw angle, in monomials of the normalized angle, and in Chebyshev polynomials of the normalized
// angle: why the fit works in the last.
#include <Eigen/Dense>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <functional>
#include <random>
#include <string>
#include <vector>

#include "fit/polyfit.h"

namespace {

using flarelab::fit::PolyFit;
using flarelab::fit::PolyFitOptions;

struct TestFunction {
    const char* name;
    std::function<double(double)> f;  // of the angle in degrees
};

std::vector<double> linspace(double a, double b, int n) {
    std::vector<double> out(n);
    for (int i = 0; i < n; ++i) out[i] = a + (b - a) * i / (n - 1);
    return out;
}

// RMS against the truth on 1000 angles strictly between the ends, none of them a sample angle
// of the sweeps below (offset by an irrational fraction of the step).
double heldOutRms(const PolyFit& fit, const std::function<double(double)>& f) {
    constexpr int kProbes = 1000;
    double sum_sq = 0.0;
    for (int i = 0; i < kProbes; ++i) {
        const double a = 30.0 * (i + 0.5 / std::sqrt(2.0)) / kProbes;
        const flarelab::Result<double> v = flarelab::fit::evaluatePolyFit(fit, a);
        if (!v) {
            std::fprintf(stderr, "evaluate: %s\n", v.error().message.c_str());
            std::exit(1);
        }
        sum_sq += (*v - f(a)) * (*v - f(a));
    }
    return std::sqrt(sum_sq / kProbes);
}

double conditionNumber(const Eigen::MatrixXd& a) {
    const Eigen::JacobiSVD<Eigen::MatrixXd> svd(a);
    const Eigen::VectorXd s = svd.singularValues();
    return s(0) / s(s.size() - 1);
}

// Design matrices at degree `degree` for angles lo..hi deg, n samples.
Eigen::MatrixXd monomialDesign(const std::vector<double>& t, int degree) {
    Eigen::MatrixXd a(static_cast<Eigen::Index>(t.size()), degree + 1);
    for (size_t i = 0; i < t.size(); ++i)
        for (int k = 0; k <= degree; ++k) a(i, k) = std::pow(t[i], k);
    return a;
}

Eigen::MatrixXd chebyshevDesign(const std::vector<double>& x, int degree) {
    Eigen::MatrixXd a(static_cast<Eigen::Index>(x.size()), degree + 1);
    for (size_t i = 0; i < x.size(); ++i) {
        std::vector<double> unit(degree + 1, 0.0);
        for (int k = 0; k <= degree; ++k) {
            unit.assign(degree + 1, 0.0);
            unit[k] = 1.0;
            a(i, k) = flarelab::fit::chebyshevValue(unit, x[i]);
        }
    }
    return a;
}

}  // namespace

int main(int argc, char** argv) {
    const int seeds = argc > 1 ? std::atoi(argv[1]) : 5;
    if (seeds < 1) {
        std::fprintf(stderr, "usage: polyfit_bench [seeds >= 1]\n");
        return 2;
    }
    const std::vector<TestFunction> functions = {
        {"sine", [](double a) { return 0.5 + 0.3 * std::sin(a / 10.0); }},
        {"damped cos", [](double a) { return std::exp(-a / 12.0) * std::cos(a / 5.0); }},
        {"bump", [](double a) { return 1.0 / (1.0 + (a - 12.0) * (a - 12.0) / 36.0); }},
    };
    const std::vector<int> counts = {151, 61, 31, 16};
    const std::vector<double> noise_levels = {0.0, 1e-3, 1e-2, 3e-2};
    constexpr int kMaxFixed = 8;

    std::printf("## Degree choice and held-out error (0..30 deg, %d seeds per row)\n\n", seeds);
    std::printf(
        "Held-out error: RMS against the noise-free function at 1000 angles between samples, mean "
        "over seeds. `auto`: cross-validated degree (one-standard-error rule), pieces "
        "allowed.\n\n");
    std::printf("| function | n | noise σ | degree chosen | pieces | fit µs | auto |");
    for (int d = 1; d <= kMaxFixed; ++d) std::printf(" deg %d |", d);
    std::printf("\n|---|---:|---:|---:|---:|---:|---:|");
    for (int d = 1; d <= kMaxFixed; ++d) std::printf("---:|");
    std::printf("\n");
    for (const TestFunction& fn : functions) {
        for (const int n : counts) {
            for (const double sigma : noise_levels) {
                const std::vector<double> angles = linspace(0.0, 30.0, n);
                int degree_min = 1000;
                int degree_max = -1;
                int pieces_max = 0;
                double auto_rms = 0.0;
                double fit_us = 0.0;
                std::vector<double> fixed_rms(kMaxFixed + 1, 0.0);
                for (int seed = 0; seed < seeds; ++seed) {
                    std::mt19937_64 rng(1000 * seed + n);
                    std::normal_distribution<double> noise(0.0, 1.0);
                    std::vector<double> values;
                    for (const double a : angles) values.push_back(fn.f(a) + sigma * noise(rng));
                    const auto start = std::chrono::steady_clock::now();
                    const flarelab::Result<PolyFit> fit =
                        flarelab::fit::fitPolynomial(angles, values);
                    fit_us += std::chrono::duration<double, std::micro>(
                                  std::chrono::steady_clock::now() - start)
                                  .count();
                    if (!fit) {
                        std::fprintf(stderr, "fit: %s\n", fit.error().message.c_str());
                        return 1;
                    }
                    for (const auto& piece : fit->pieces) {
                        degree_min = std::min(degree_min, piece.degree());
                        degree_max = std::max(degree_max, piece.degree());
                    }
                    pieces_max = std::max(pieces_max, static_cast<int>(fit->pieces.size()));
                    auto_rms += heldOutRms(*fit, fn.f);
                    for (int d = 1; d <= kMaxFixed && d < n; ++d) {
                        PolyFitOptions options;
                        options.fixed_degree = d;
                        const flarelab::Result<PolyFit> fixed =
                            flarelab::fit::fitPolynomial(angles, values, options);
                        if (!fixed) return 1;
                        fixed_rms[d] += heldOutRms(*fixed, fn.f);
                    }
                }
                const std::string degrees =
                    degree_min == degree_max
                        ? std::to_string(degree_min)
                        : std::to_string(degree_min) + "–" + std::to_string(degree_max);
                std::printf("| %s | %d | %.0e | %s | %d | %.0f | %.1e |", fn.name, n, sigma,
                            degrees.c_str(), pieces_max, fit_us / seeds, auto_rms / seeds);
                for (int d = 1; d <= kMaxFixed; ++d) {
                    if (d < n)
                        std::printf(" %.1e |", fixed_rms[d] / seeds);
                    else
                        std::printf(" — |");
                }
                std::printf("\n");
            }
        }
    }

    std::printf("\n## Condition number of the degree-8 design matrix\n\n");
    std::printf(
        "| angles | n | monomials of angle | monomials of normalized angle | Chebyshev of "
        "normalized angle |\n|---|---:|---:|---:|---:|\n");
    constexpr int kDegree = 8;
    for (const double offset : {0.0, 1e6}) {
        for (const int n : counts) {
            const std::vector<double> angles = linspace(offset, offset + 30.0, n);
            std::vector<double> x;
            for (const double a : angles) x.push_back(2.0 * ((a - offset) / 30.0) - 1.0);
            std::printf("| %s | %d | %.2e | %.2e | %.2e |\n",
                        offset == 0.0 ? "0–30 deg" : "1e6 + 0–30 deg", n,
                        conditionNumber(monomialDesign(angles, kDegree)),
                        conditionNumber(monomialDesign(x, kDegree)),
                        conditionNumber(chebyshevDesign(x, kDegree)));
        }
    }
    return 0;
}
