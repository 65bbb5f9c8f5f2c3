// VAMP's Panda collision check timed in C++ (no Python binding in the loop).
//
// Compiled against the headers of the vamp-planner
// source package (header-only: vamp/robots/panda.hh) and Eigen; run by
// benchmarks/bench_limit.py.  Not part of gcm_pipeline.
//
//   vamp_bench SCENE CONFIGS N BLOCK_CONFIGS M REPEATS OUT
//
// SCENE: text, one primitive a line:
//   cuboid cx cy cz  ex ey ez  hx hy hz      (centre, Euler XYZ, half extents)
//   capsule cx cy cz  ex ey ez  r length     (centre, Euler XYZ, radius, segment length along local z)
//   sphere cx cy cz r
// CONFIGS: N x 7 float32 (raw), checked one per call exactly as VAMP's
// `validate` does (one SIMD block whose lanes all hold the configuration:
// validate_motion<Panda, rake, 1>(q, q, env)); their validity (one byte each) goes to OUT.
// BLOCK_CONFIGS: M x 7 float32, checked in blocks of `rake` distinct
// configurations (Panda::fkcc<rake> on one block: true when every lane is free).
// Prints JSON: median seconds per configuration of both loops over REPEATS.
#include <vamp/robots/panda.hh>
#include <vamp/collision/factory.hh>
#include <vamp/planning/validate.hh>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

using Robot = vamp::robots::Panda;
static constexpr std::size_t rake = vamp::FloatVectorWidth;
namespace vc = vamp::collision;
namespace vf = vamp::collision::factory;

static auto read_floats(const char *path, std::size_t n) -> std::vector<float>
{
    std::vector<float> out(n * Robot::dimension);
    std::ifstream f(path, std::ios::binary);
    f.read(reinterpret_cast<char *>(out.data()), static_cast<std::streamsize>(out.size() * sizeof(float)));
    if (!f)
    {
        std::fprintf(stderr, "vamp_bench: cannot read %zu configurations from %s\n", n, path);
        std::exit(2);
    }
    return out;
}

static auto read_scene(const char *path) -> vc::Environment<float>
{
    vc::Environment<float> env;
    std::ifstream f(path);
    std::string line;
    while (std::getline(f, line))
    {
        std::istringstream s(line);
        std::string kind;
        s >> kind;
        if (kind == "cuboid")
        {
            std::array<float, 3> c, e, h;
            s >> c[0] >> c[1] >> c[2] >> e[0] >> e[1] >> e[2] >> h[0] >> h[1] >> h[2];
            auto box = vf::cuboid::array(c, e, h);
            (box.axis_3_z == 1.F ? env.z_aligned_cuboids : env.cuboids).emplace_back(box);
        }
        else if (kind == "capsule")
        {
            std::array<float, 3> c, e;
            float r, len;
            s >> c[0] >> c[1] >> c[2] >> e[0] >> e[1] >> e[2] >> r >> len;
            auto cap = vf::cylinder::center::array(c, e, r, len);
            (cap.xv == 0.F && cap.yv == 0.F ? env.z_aligned_capsules : env.capsules).emplace_back(cap);
        }
        else if (kind == "sphere")
        {
            std::array<float, 3> c;
            float r;
            s >> c[0] >> c[1] >> c[2] >> r;
            env.spheres.emplace_back(vf::sphere::array(c, r));
        }
        else if (!kind.empty())
        {
            std::fprintf(stderr, "vamp_bench: unknown primitive %s\n", kind.c_str());
            std::exit(2);
        }
    }
    env.sort();
    return env;
}

template <typename F>
static auto median_seconds(int repeats, F &&fn) -> double
{
    std::vector<double> t;
    for (int r = 0; r < repeats; ++r)
    {
        auto t0 = std::chrono::steady_clock::now();
        fn();
        t.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
    }
    std::sort(t.begin(), t.end());
    return t[t.size() / 2];
}

int main(int argc, char **argv)
{
    if (argc != 8)
    {
        std::fprintf(stderr, "usage: vamp_bench SCENE CONFIGS N BLOCK_CONFIGS M REPEATS OUT\n");
        return 2;
    }
    const auto env = vc::Environment<vamp::FloatVector<rake>>(read_scene(argv[1]));
    const std::size_t n = std::stoul(argv[3]), m = std::stoul(argv[5]);
    const int repeats = std::stoi(argv[6]);
    const auto q = read_floats(argv[2], n);
    const auto qb = read_floats(argv[4], m);

    std::vector<Robot::Configuration> one;
    for (std::size_t i = 0; i < n; ++i)
    {
        Robot::ConfigurationArray a;
        std::copy_n(q.begin() + i * Robot::dimension, Robot::dimension, a.begin());
        one.emplace_back(a);
    }
    std::vector<Robot::ConfigurationBlock<rake>> blocks;
    for (std::size_t b = 0; b + rake <= m; b += rake)
    {
        Robot::ConfigurationBlock<rake> block;
        for (std::size_t j = 0; j < Robot::dimension; ++j)
        {
            std::array<float, rake> lane;
            for (std::size_t k = 0; k < rake; ++k)
            {
                lane[k] = qb[(b + k) * Robot::dimension + j];
            }
            block[j] = vamp::FloatVector<rake>(lane);
        }
        blocks.push_back(block);
    }

    std::vector<unsigned char> valid(n);
    const double t_one = median_seconds(
        repeats,
        [&]
        {
            for (std::size_t i = 0; i < n; ++i)
            {
                valid[i] = vamp::planning::validate_motion<Robot, rake, 1>(one[i], one[i], env);
            }
        });
    std::size_t free_blocks = 0;
    const double t_block = median_seconds(
        repeats,
        [&]
        {
            free_blocks = 0;
            for (const auto &block : blocks)
            {
                free_blocks += Robot::fkcc<rake>(env, block);
            }
        });
    std::ofstream(argv[7], std::ios::binary)
        .write(reinterpret_cast<const char *>(valid.data()), static_cast<std::streamsize>(n));
    std::printf(
        "{\"one_per_call_s_per_config\": %.6e, \"block_s_per_config\": %.6e, \"blocks\": %zu, "
        "\"free_blocks\": %zu, \"rake\": %zu}\n",
        n ? t_one / n : 0.0,
        blocks.empty() ? 0.0 : t_block / (blocks.size() * rake),
        blocks.size(),
        free_blocks,
        rake);
    return 0;
}
