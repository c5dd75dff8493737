// Read one conformance case (an uncompressed .npz) in plain C++17, no libraries.
//
//   g++ -std=c++17 -O2 -o read_case examples/conformance/read_case.cpp
//   ./read_case golden/sim3.act/edges.npz            # list the entries
//   ./read_case golden/sim3.act/edges.npz --act      # check a Sim(3) action against out.P
//
// A case file is a zip archive whose entries are *stored* (method 0) .npy files. The central
// directory at the end of the archive gives each entry's name, size and the offset of its
// local header (numpy writes ZIP64 local headers, so the central directory is the reliable
// source of the sizes). A .npy file is the magic "\x93NUMPY", a version, a little-endian
// header length, a Python-dict header ('descr', 'fortran_order', 'shape') and the raw data.
// Golden sets use only '<f8', '<i8' and '|b1', in C order.
//
// --act is a worked conformance check: it computes P = s R(q) X + t for every row of in.T
// ([tx, ty, tz, qx, qy, qz, qw, s]) and in.X, and compares with the reference's out.P using the
// tolerance index.json gives kernel sim3.act at f64: |P - ref| <= 1e-9 + 1e-9 |ref|.
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <iterator>
#include <map>
#include <stdexcept>
#include <string>
#include <vector>

struct Array {
  std::string descr;            // '<f8', '<i8' or '|b1'
  std::vector<size_t> shape;    // C order
  std::vector<uint8_t> bytes;   // raw little-endian data
  size_t size() const {
    size_t n = 1;
    for (size_t d : shape) n *= d;
    return n;
  }
  double at(size_t i) const {   // entry i as a double, whatever the dtype
    if (descr == "<f8") { double v; std::memcpy(&v, &bytes[8 * i], 8); return v; }
    if (descr == "<i8") { int64_t v; std::memcpy(&v, &bytes[8 * i], 8); return double(v); }
    if (descr == "|b1") return bytes[i] ? 1.0 : 0.0;
    throw std::runtime_error("unsupported dtype " + descr);
  }
};

static uint64_t le(const std::vector<uint8_t>& b, size_t at, int n) {
  if (at + n > b.size()) throw std::runtime_error("truncated file");
  uint64_t v = 0;
  for (int k = n - 1; k >= 0; --k) v = (v << 8) | b[at + k];
  return v;
}

// The text between `key': ` and the next delimiter of a .npy header dict.
static std::string field(const std::string& h, const std::string& key) {
  size_t at = h.find("'" + key + "':");
  if (at == std::string::npos) throw std::runtime_error("npy header lacks " + key);
  at = h.find_first_not_of(' ', at + key.size() + 3);
  return at == std::string::npos ? "" : h.substr(at);
}

static Array parse_npy(const std::vector<uint8_t>& b, size_t at, size_t len) {
  if (len < 10 || std::memcmp(&b[at], "\x93NUMPY", 6) != 0) throw std::runtime_error("not npy");
  int major = b[at + 6];
  size_t hlen = major == 1 ? le(b, at + 8, 2) : le(b, at + 8, 4);
  size_t start = at + (major == 1 ? 10 : 12);
  std::string h(b.begin() + start, b.begin() + start + hlen);
  Array a;
  std::string d = field(h, "descr");
  a.descr = d.substr(d.find('\'') + 1, 3);
  if (field(h, "fortran_order").rfind("False", 0) != 0)
    throw std::runtime_error("fortran order not supported");
  std::string s = field(h, "shape");
  s = s.substr(s.find('(') + 1, s.find(')') - s.find('(') - 1);
  for (size_t p = 0; p < s.size();) {
    size_t q = s.find(',', p);
    std::string tok = s.substr(p, q == std::string::npos ? std::string::npos : q - p);
    if (tok.find_first_of("0123456789") != std::string::npos) a.shape.push_back(std::stoul(tok));
    if (q == std::string::npos) break;
    p = q + 1;
  }
  size_t item = a.descr == "|b1" ? 1 : 8;
  size_t data = start + hlen;
  if (data + a.size() * item > at + len) throw std::runtime_error("npy data truncated");
  a.bytes.assign(b.begin() + data, b.begin() + data + a.size() * item);
  return a;
}

// Every entry of a stored .npz, by name without ".npy".
static std::map<std::string, Array> read_npz(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  if (!f) throw std::runtime_error("cannot open " + path);
  std::vector<uint8_t> b((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  size_t eocd = b.size() >= 22 ? b.size() - 22 : 0;
  while (eocd > 0 && le(b, eocd, 4) != 0x06054b50) --eocd;  // end of central directory
  if (le(b, eocd, 4) != 0x06054b50) throw std::runtime_error("not a zip archive");
  size_t n = le(b, eocd + 10, 2), at = le(b, eocd + 16, 4);
  std::map<std::string, Array> out;
  for (size_t k = 0; k < n; ++k) {
    if (le(b, at, 4) != 0x02014b50) throw std::runtime_error("bad central directory");
    size_t method = le(b, at + 10, 2), csize = le(b, at + 20, 4);
    size_t nlen = le(b, at + 28, 2), xlen = le(b, at + 30, 2), clen = le(b, at + 32, 2);
    size_t local = le(b, at + 42, 4);
    std::string name(b.begin() + at + 46, b.begin() + at + 46 + nlen);
    for (size_t x = at + 46 + nlen; x + 4 <= at + 46 + nlen + xlen;) {  // ZIP64 extra field
      size_t id = le(b, x, 2), sz = le(b, x + 2, 2), p = x + 4;
      if (id == 1) {
        if (le(b, at + 24, 4) == 0xffffffff) p += 8;  // uncompressed size comes first
        if (csize == 0xffffffff) { csize = le(b, p, 8); p += 8; }
        if (local == 0xffffffff) local = le(b, p, 8);
      }
      x += 4 + sz;
    }
    if (method != 0) throw std::runtime_error(name + ": compressed entry (write with np.savez)");
    size_t data = local + 30 + le(b, local + 26, 2) + le(b, local + 28, 2);
    out[name.substr(0, name.size() - 4)] = parse_npy(b, data, csize);
    at += 46 + nlen + xlen + clen;
  }
  return out;
}

// The worked check: P = s R(q) X + t, q = (x, y, z, w) normalised, against out.P.
static int check_act(std::map<std::string, Array>& c) {
  const Array &T = c.at("in.T"), &X = c.at("in.X"), &P = c.at("out.P");
  size_t rows = T.size() / 8;
  if (X.size() != 3 * rows || P.size() != 3 * rows) {
    std::printf("--act needs one point per pose (no broadcasting in this example)\n");
    return 2;
  }
  double worst = 0.0;
  bool ok = true;
  for (size_t r = 0; r < rows; ++r) {
    double t[3], q[4], x[3], s = T.at(8 * r + 7);
    for (int k = 0; k < 3; ++k) t[k] = T.at(8 * r + k), x[k] = X.at(3 * r + k);
    double qn = 0.0;
    for (int k = 0; k < 4; ++k) q[k] = T.at(8 * r + 3 + k), qn += q[k] * q[k];
    for (double& v : q) v /= std::sqrt(qn);
    const double qx = q[0], qy = q[1], qz = q[2], qw = q[3];
    const double R[3][3] = {
        {1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)},
        {2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)},
        {2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)}};
    for (int i = 0; i < 3; ++i) {
      double p = s * (R[i][0] * x[0] + R[i][1] * x[1] + R[i][2] * x[2]) + t[i];
      double ref = P.at(3 * r + i), err = std::fabs(p - ref);
      worst = std::fmax(worst, err);
      ok = ok && err <= 1e-9 + 1e-9 * std::fabs(ref);
    }
  }
  std::printf("sim3.act: %zu points, max |P - ref| = %.3e: %s\n", rows, worst, ok ? "ok" : "FAIL");
  return ok ? 0 : 1;
}

int main(int argc, char** argv) {
  if (argc < 2) {
    std::fprintf(stderr, "usage: %s CASE.npz [--act]\n", argv[0]);
    return 2;
  }
  try {
    auto c = read_npz(argv[1]);
    if (argc > 2 && std::string(argv[2]) == "--act") return check_act(c);
    for (auto& [name, a] : c) {
      std::printf("%s %s (", name.c_str(), a.descr.c_str());
      for (size_t k = 0; k < a.shape.size(); ++k) std::printf(k ? ", %zu" : "%zu", a.shape[k]);
      std::printf(")");
      if (a.size()) std::printf(" first=%.17g", a.at(0));
      std::printf("\n");
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "%s: %s\n", argv[1], e.what());
    return 2;
  }
  return 0;
}
