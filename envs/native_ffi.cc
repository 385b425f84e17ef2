// The `mujoco` backend's env step and reset as XLA FFI handlers (see native_ffi.py).
//
// The arithmetic is envs/native.py's host_step / host_reset, operation for operation, on the
// same libmujoco that mjbatch steps with: the result is bit for bit the pure_callback path's
// (tests/test_native_ffi.py). A compiled program refers to a handler by name and to a task by
// an integer id that hashes its model and layout, never by a pointer, so the programs that
// hold the physics can be kept in JAX's persistent compilation cache.
//
// Compile without fused multiply-adds (-ffp-contract=off, no -march): numpy does not fuse.

#include <mujoco/mujoco.h>

#include <cstdint>
#include <cstring>
#include <map>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

// Layout of the int64 array that rdher_register receives (native_ffi.py, _layout).
enum Field : int {
  kNstate, kOffQpos, kOffQvel, kOffCtrl, kOffMocapPos, kOffMocapQuat, kNq, kNv,
  kBlockGripper, kHasObject, kGripSite, kObjectSite, kGripperBody, kGripRoot, kObjectRoot,
  kFingerQpos0, kFingerQpos1, kFingerDof0, kFingerDof1, kNumThreads, kRawSize,
  kRawGripPos, kRawGripVelp, kRawObjPos, kRawObjXmat, kRawObjVelp, kRawObjVelr,
  kRawFingerQpos, kRawFingerQvel, kNAct, kNGripChain, kNObjectChain, kNumFields
};
constexpr int kRef = 7;  // gripper body xpos (3) + xquat (4)

struct Task {
  const mjModel* m = nullptr;
  std::vector<int64_t> f;  // kNumFields values
  std::vector<int64_t> act_qposadr, grip_chain, object_chain;
  std::vector<double> tmpl;  // the reset template state (nstate)
  std::mutex mu;
  std::vector<mjData*> data;  // one per batch index, grown on demand
  ~Task() {
    for (mjData* d : data) mj_deleteData(d);
  }
  int64_t width() const { return f[kNstate] + kRef; }
};

std::mutex g_mu;
std::map<int64_t, std::unique_ptr<Task>> g_tasks;

Task* find(int64_t id) {
  std::lock_guard<std::mutex> lock(g_mu);
  auto it = g_tasks.find(id);
  return it == g_tasks.end() ? nullptr : it->second.get();
}

void site_vel(const Task& t, const mjData* d, const double* state, int site, int root,
              const std::vector<int64_t>& chain, double* velp, double* velr) {
  const double* qvel = state + t.f[kOffQvel];
  double offset[3];
  for (int x = 0; x < 3; ++x) offset[x] = d->site_xpos[3 * site + x] - d->subtree_com[3 * root + x];
  for (int x = 0; x < 3; ++x) velp[x] = velr[x] = 0.0;
  for (size_t k = 0; k < chain.size(); ++k) {
    const double* cd = d->cdof + 6 * chain[k];
    const double q = qvel[chain[k]];
    const double jp[3] = {cd[3] + (cd[1] * offset[2] - cd[2] * offset[1]),
                          cd[4] + (cd[2] * offset[0] - cd[0] * offset[2]),
                          cd[5] + (cd[0] * offset[1] - cd[1] * offset[0])};
    for (int x = 0; x < 3; ++x) {
      velp[x] += jp[x] * q;
      velr[x] += cd[x] * q;
    }
  }
}

// The readout of envs/native.py's _readout, then the packing of _pack.
void readout(const Task& t, const mjData* d, const double* state, uint32_t* bits_out,
             float* raw_out) {
  const auto& f = t.f;
  std::vector<double> raw(f[kRawSize], 0.0);
  for (int x = 0; x < 3; ++x) raw[f[kRawGripPos] + x] = d->site_xpos[3 * f[kGripSite] + x];
  double velp[3], velr[3];
  site_vel(t, d, state, f[kGripSite], f[kGripRoot], t.grip_chain, velp, velr);
  for (int x = 0; x < 3; ++x) raw[f[kRawGripVelp] + x] = velp[x];
  if (f[kHasObject]) {
    const int os = f[kObjectSite];
    for (int x = 0; x < 3; ++x) raw[f[kRawObjPos] + x] = d->site_xpos[3 * os + x];
    for (int x = 0; x < 9; ++x) raw[f[kRawObjXmat] + x] = d->site_xmat[9 * os + x];
    site_vel(t, d, state, os, f[kObjectRoot], t.object_chain, velp, velr);
    for (int x = 0; x < 3; ++x) {
      raw[f[kRawObjVelp] + x] = velp[x];
      raw[f[kRawObjVelr] + x] = velr[x];
    }
  }
  const double* qpos = state + f[kOffQpos];
  const double* qvel = state + f[kOffQvel];
  raw[f[kRawFingerQpos]] = qpos[f[kFingerQpos0]];
  raw[f[kRawFingerQpos] + 1] = qpos[f[kFingerQpos1]];
  raw[f[kRawFingerQvel]] = qvel[f[kFingerDof0]];
  raw[f[kRawFingerQvel] + 1] = qvel[f[kFingerDof1]];
  for (int64_t i = 0; i < f[kRawSize]; ++i) raw_out[i] = static_cast<float>(raw[i]);

  const int64_t n = f[kNstate];
  std::memcpy(bits_out, state, sizeof(double) * n);
  const int gb = f[kGripperBody];
  double ref[kRef];
  for (int x = 0; x < 3; ++x) ref[x] = d->xpos[3 * gb + x];
  for (int x = 0; x < 4; ++x) ref[3 + x] = d->xquat[4 * gb + x];
  std::memcpy(bits_out + 2 * n, ref, sizeof(ref));
}

mjData* data_for(Task& t, size_t i) {
  // Called with t.mu held.
  while (t.data.size() <= i) t.data.push_back(mj_makeData(t.m));
  return t.data[i];
}

// Run fn(i) for i in [0, n) on up to f[kNumThreads] threads.
template <typename Fn>
void parallel(const Task& t, int64_t n, Fn fn) {
  const int64_t threads = std::max<int64_t>(1, std::min<int64_t>(t.f[kNumThreads], n));
  if (threads == 1) {
    for (int64_t i = 0; i < n; ++i) fn(i);
    return;
  }
  std::vector<std::thread> pool;
  for (int64_t w = 1; w < threads; ++w)
    pool.emplace_back([&, w] {
      for (int64_t i = w; i < n; i += threads) fn(i);
    });
  for (int64_t i = 0; i < n; i += threads) fn(i);
  for (auto& th : pool) th.join();
}

// Run fn(i, data) for every batch index i in [0, n), each on its own mjData, holding the task
// (its data grown to n) for the call.
template <typename Fn>
void for_each_env(Task& t, int64_t n, Fn fn) {
  std::lock_guard<std::mutex> lock(t.mu);
  for (int64_t i = 0; i < n; ++i) data_for(t, i);
  parallel(t, n, [&](int64_t i) { fn(i, t.data[i]); });
}

constexpr double kMocapQuatDelta[4] = {1.0, 0.0, 1.0, 0.0};
constexpr char kUnregistered[] = "rdher_jax: physics task not registered";

ffi::Error Step(int64_t task_id, ffi::Buffer<ffi::U32> bits, ffi::Buffer<ffi::F32> delta,
                ffi::Buffer<ffi::F32> grip, ffi::ResultBuffer<ffi::U32> bits_out,
                ffi::ResultBuffer<ffi::F32> raw_out) {
  Task* tp = find(task_id);
  if (!tp) return ffi::Error::InvalidArgument(kUnregistered);
  Task& t = *tp;
  const auto& f = t.f;
  const int64_t width = t.width(), nstate = f[kNstate];
  const int64_t n = delta.element_count() / 3;
  if (bits.element_count() != n * 2 * width || grip.element_count() != n)
    return ffi::Error::InvalidArgument("rdher_jax: physics step got inconsistent shapes");
  const double* full = reinterpret_cast<const double*>(bits.typed_data());
  const float* dl = delta.typed_data();
  const float* gr = grip.typed_data();
  uint32_t* bo = bits_out->typed_data();
  float* ro = raw_out->typed_data();
  for_each_env(t, n, [&](int64_t i, mjData* d) {
    std::vector<double> state(full + i * width, full + i * width + nstate);
    const double* ref = full + i * width + nstate;
    for (int x = 0; x < 3; ++x)
      state[f[kOffMocapPos] + x] = ref[x] + static_cast<double>(dl[3 * i + x]);
    for (int x = 0; x < 4; ++x) state[f[kOffMocapQuat] + x] = ref[3 + x] + kMocapQuatDelta[x];
    for (size_t a = 0; a < t.act_qposadr.size(); ++a)
      state[f[kOffCtrl] + a] =
          state[f[kOffQpos] + t.act_qposadr[a]] + static_cast<double>(gr[i]);
    mj_setState(t.m, d, state.data(), mjSTATE_INTEGRATION);
    for (int s = 0; s < 20; ++s) mj_step(t.m, d);
    if (f[kBlockGripper]) mj_forward(t.m, d);
    mj_getState(t.m, d, state.data(), mjSTATE_INTEGRATION);
    if (f[kBlockGripper]) {
      state[f[kOffQpos] + f[kFingerQpos0]] = 0.0;
      state[f[kOffQpos] + f[kFingerQpos1]] = 0.0;
    }
    readout(t, d, state.data(), bo + i * 2 * width, ro + i * f[kRawSize]);
  });
  return ffi::Error::Success();
}

ffi::Error Reset(int64_t task_id, ffi::Buffer<ffi::F32> qpos, ffi::Buffer<ffi::F32> qvel,
                 ffi::ResultBuffer<ffi::U32> bits_out, ffi::ResultBuffer<ffi::F32> raw_out) {
  Task* tp = find(task_id);
  if (!tp) return ffi::Error::InvalidArgument(kUnregistered);
  Task& t = *tp;
  const auto& f = t.f;
  const int64_t width = t.width(), nq = f[kNq], nv = f[kNv];
  const int64_t n = qpos.element_count() / nq;
  if (qvel.element_count() != n * nv)
    return ffi::Error::InvalidArgument("rdher_jax: physics reset got inconsistent shapes");
  const float* qp = qpos.typed_data();
  const float* qv = qvel.typed_data();
  uint32_t* bo = bits_out->typed_data();
  float* ro = raw_out->typed_data();
  for_each_env(t, n, [&](int64_t i, mjData* d) {
    std::vector<double> state(t.tmpl);
    // Entries the caller left at the template (equal in float32) keep its float64 value.
    auto take = [&](int64_t off, const float* src, int64_t k) {
      for (int64_t j = 0; j < k; ++j) {
        const double old = state[off + j];
        const double nw = static_cast<double>(src[j]);
        state[off + j] = (nw == static_cast<double>(static_cast<float>(old))) ? old : nw;
      }
    };
    take(f[kOffQpos], qp + i * nq, nq);
    take(f[kOffQvel], qv + i * nv, nv);
    mj_setState(t.m, d, state.data(), mjSTATE_INTEGRATION);
    mj_forward(t.m, d);
    readout(t, d, state.data(), bo + i * 2 * width, ro + i * f[kRawSize]);
  });
  return ffi::Error::Success();
}

}  // namespace

extern "C" {

// Register (or re-register) a task under `id`: the model stays owned by the caller (native_ffi.py
// keeps a private copy for the life of the process) and must outlive every call. Returns 0, or
// -1 on a malformed layout.
int rdher_register(int64_t id, const mjModel* m, const int64_t* fields, int64_t nfields,
                   const int64_t* lists, const double* tmpl) {
  if (nfields != kNumFields) return -1;
  auto t = std::make_unique<Task>();
  t->m = m;
  t->f.assign(fields, fields + nfields);
  const int64_t na = t->f[kNAct], ng = t->f[kNGripChain], no = t->f[kNObjectChain];
  t->act_qposadr.assign(lists, lists + na);
  t->grip_chain.assign(lists + na, lists + na + ng);
  t->object_chain.assign(lists + na + ng, lists + na + ng + no);
  t->tmpl.assign(tmpl, tmpl + t->f[kNstate]);
  std::lock_guard<std::mutex> lock(g_mu);
  g_tasks[id] = std::move(t);
  return 0;
}

int64_t rdher_num_fields() { return kNumFields; }

}  // extern "C"

XLA_FFI_DEFINE_HANDLER_SYMBOL(RdherPhysicsStep, Step,
                              ffi::Ffi::Bind()
                                  .Attr<int64_t>("task_id")
                                  .Arg<ffi::Buffer<ffi::U32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::U32>>()
                                  .Ret<ffi::Buffer<ffi::F32>>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(RdherPhysicsReset, Reset,
                              ffi::Ffi::Bind()
                                  .Attr<int64_t>("task_id")
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::U32>>()
                                  .Ret<ffi::Buffer<ffi::F32>>());
