// EWA projection and SH colours, forward and backward (see project.h).
#include "project.h"
#include "stage_times.h"

#include <algorithm>
#include <cmath>

namespace promptgs {

namespace {

constexpr float kAlphaCut = 1.0f / 255.0f;
constexpr float kMaxExtend = 3.33f;

constexpr float C0 = 0.28209479177387814f;
constexpr float C1 = 0.4886025119029199f;
constexpr float C2[5] = {1.0925484305920792f, -1.0925484305920792f, 0.31539156525252005f, -1.0925484305920792f,
                         0.5462742152960396f};
constexpr float C3[7] = {-0.5900435899266435f, 2.890611442640554f, -0.4570457994644658f, 0.3731763325901154f,
                         -0.4570457994644658f, 1.445305721320277f, -0.5900435899266435f};

// Rotation matrix (row-major) of a unit quaternion (w, x, y, z).
inline void quat_to_rot(const float q[4], float R[9]) {
    const float w = q[0], x = q[1], y = q[2], z = q[3];
    R[0] = 1.f - 2.f * (y * y + z * z);
    R[1] = 2.f * (x * y - w * z);
    R[2] = 2.f * (x * z + w * y);
    R[3] = 2.f * (x * y + w * z);
    R[4] = 1.f - 2.f * (x * x + z * z);
    R[5] = 2.f * (y * z - w * x);
    R[6] = 2.f * (x * z - w * y);
    R[7] = 2.f * (y * z + w * x);
    R[8] = 1.f - 2.f * (x * x + y * y);
}

// C = A B for 3x3 row-major matrices; At/Bt use the transpose of A/B.
__attribute__((always_inline)) inline void mul33(const float* A, const float* B, float* C, bool At = false, bool Bt = false) {
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            float s = 0.f;
            for (int k = 0; k < 3; ++k) s += (At ? A[k * 3 + i] : A[i * 3 + k]) * (Bt ? B[j * 3 + k] : B[k * 3 + j]);
            C[i * 3 + j] = s;
        }
}

// Everything the forward computes for one Gaussian that the backward needs again.
struct Proj {
    float qn[4], qnorm;
    float Rq[9], M[9];
    float pc[3];
    float covc[9];  // camera-space 3D covariance
    float J[6];     // 2x3 Jacobian, row-major
    float tx, ty;
    bool clamp_x, clamp_y;
    float c00, c01, c11, det;
};

// Projects Gaussian i; returns false when it is culled before the 2D covariance exists.
__attribute__((always_inline)) inline bool project_one(const ProjectInputs& in, const Camera& cam, int64_t i, Proj& p) {
    const float* m = in.means + 3 * i;
    for (int r = 0; r < 3; ++r) p.pc[r] = cam.R[3 * r] * m[0] + cam.R[3 * r + 1] * m[1] + cam.R[3 * r + 2] * m[2] + cam.t[r];
    const float z = p.pc[2];
    if (!(z > cam.near_plane && z < cam.far_plane)) return false;

    const float* q = in.quats + 4 * i;
    p.qnorm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    const float inv = 1.f / std::max(p.qnorm, 1e-12f);
    for (int k = 0; k < 4; ++k) p.qn[k] = q[k] * inv;
    quat_to_rot(p.qn, p.Rq);
    const float* s = in.scales + 3 * i;
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) p.M[3 * r + c] = p.Rq[3 * r + c] * s[c];
    float cov[9], tmp[9];
    mul33(p.M, p.M, cov, false, true);        // M M^T
    mul33(cam.R, cov, tmp);                   // R Σ
    mul33(tmp, cam.R, p.covc, false, true);   // R Σ R^T

    const float tan_fovx = 0.5f * cam.width / cam.fx, tan_fovy = 0.5f * cam.height / cam.fy;
    const float lim_xp = (cam.width - cam.cx) / cam.fx + 0.3f * tan_fovx;
    const float lim_xn = cam.cx / cam.fx + 0.3f * tan_fovx;
    const float lim_yp = (cam.height - cam.cy) / cam.fy + 0.3f * tan_fovy;
    const float lim_yn = cam.cy / cam.fy + 0.3f * tan_fovy;
    const float rx = p.pc[0] / z, ry = p.pc[1] / z;
    p.clamp_x = rx < -lim_xn || rx > lim_xp;
    p.clamp_y = ry < -lim_yn || ry > lim_yp;
    p.tx = z * std::min(std::max(rx, -lim_xn), lim_xp);
    p.ty = z * std::min(std::max(ry, -lim_yn), lim_yp);
    const float iz = 1.f / z, iz2 = iz * iz;
    p.J[0] = cam.fx * iz;
    p.J[1] = 0.f;
    p.J[2] = -cam.fx * p.tx * iz2;
    p.J[3] = 0.f;
    p.J[4] = cam.fy * iz;
    p.J[5] = -cam.fy * p.ty * iz2;
    // cov2d = J covc J^T
    float T[6];
    for (int r = 0; r < 2; ++r)
        for (int c = 0; c < 3; ++c)
            T[3 * r + c] = p.J[3 * r] * p.covc[c] + p.J[3 * r + 1] * p.covc[3 + c] + p.J[3 * r + 2] * p.covc[6 + c];
    const float cov00 = T[0] * p.J[0] + T[1] * p.J[1] + T[2] * p.J[2];
    const float cov01 = T[0] * p.J[3] + T[1] * p.J[4] + T[2] * p.J[5];
    const float cov10 = T[3] * p.J[0] + T[4] * p.J[1] + T[5] * p.J[2];
    const float cov11 = T[3] * p.J[3] + T[4] * p.J[4] + T[5] * p.J[5];
    p.c00 = cov00 + cam.eps2d;
    p.c11 = cov11 + cam.eps2d;
    p.c01 = 0.5f * (cov01 + cov10);
    p.det = p.c00 * p.c11 - p.c01 * p.c01;
    return p.det > 0.f;
}

inline void sh_bases(int degree, float x, float y, float z, float* B) {
    B[0] = C0;
    if (degree < 1) return;
    B[1] = -C1 * y;
    B[2] = C1 * z;
    B[3] = -C1 * x;
    if (degree < 2) return;
    const float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    B[4] = C2[0] * xy;
    B[5] = C2[1] * yz;
    B[6] = C2[2] * (2.f * zz - xx - yy);
    B[7] = C2[3] * xz;
    B[8] = C2[4] * (xx - yy);
    if (degree < 3) return;
    B[9] = C3[0] * y * (3.f * xx - yy);
    B[10] = C3[1] * xy * z;
    B[11] = C3[2] * y * (4.f * zz - xx - yy);
    B[12] = C3[3] * z * (2.f * zz - 3.f * xx - 3.f * yy);
    B[13] = C3[4] * x * (4.f * zz - xx - yy);
    B[14] = C3[5] * z * (xx - yy);
    B[15] = C3[6] * x * (xx - 3.f * yy);
}

// d = sum_k vB[k] * grad B_k at the (unit) direction (x, y, z), as functions on R^3.
inline void sh_bases_grad(int degree, float x, float y, float z, const float* vB, float d[3]) {
    d[0] = d[1] = d[2] = 0.f;
    if (degree < 1) return;
    d[1] += -C1 * vB[1];
    d[2] += C1 * vB[2];
    d[0] += -C1 * vB[3];
    if (degree < 2) return;
    const float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    d[0] += C2[0] * y * vB[4];
    d[1] += C2[0] * x * vB[4];
    d[1] += C2[1] * z * vB[5];
    d[2] += C2[1] * y * vB[5];
    d[0] += -2.f * C2[2] * x * vB[6];
    d[1] += -2.f * C2[2] * y * vB[6];
    d[2] += 4.f * C2[2] * z * vB[6];
    d[0] += C2[3] * z * vB[7];
    d[2] += C2[3] * x * vB[7];
    d[0] += 2.f * C2[4] * x * vB[8];
    d[1] += -2.f * C2[4] * y * vB[8];
    if (degree < 3) return;
    d[0] += C3[0] * 6.f * xy * vB[9];
    d[1] += C3[0] * (3.f * xx - 3.f * yy) * vB[9];
    d[0] += C3[1] * yz * vB[10];
    d[1] += C3[1] * xz * vB[10];
    d[2] += C3[1] * xy * vB[10];
    d[0] += C3[2] * (-2.f * xy) * vB[11];
    d[1] += C3[2] * (4.f * zz - xx - 3.f * yy) * vB[11];
    d[2] += C3[2] * 8.f * yz * vB[11];
    d[0] += C3[3] * (-6.f * xz) * vB[12];
    d[1] += C3[3] * (-6.f * yz) * vB[12];
    d[2] += C3[3] * (6.f * zz - 3.f * xx - 3.f * yy) * vB[12];
    d[0] += C3[4] * (4.f * zz - 3.f * xx - yy) * vB[13];
    d[1] += C3[4] * (-2.f * xy) * vB[13];
    d[2] += C3[4] * 8.f * xz * vB[13];
    d[0] += C3[5] * 2.f * xz * vB[14];
    d[1] += C3[5] * (-2.f * yz) * vB[14];
    d[2] += C3[5] * (xx - yy) * vB[14];
    d[0] += C3[6] * (3.f * xx - 3.f * yy) * vB[15];
    d[1] += C3[6] * (-6.f * xy) * vB[15];
}

inline void camera_center(const Camera& cam, float c[3]) {
    for (int j = 0; j < 3; ++j) c[j] = -(cam.R[j] * cam.t[0] + cam.R[3 + j] * cam.t[1] + cam.R[6 + j] * cam.t[2]);
}

// The 3 values of SH coefficient k of Gaussian i in (sh, sh_rest) as ProjectInputs lays them out.
template <typename T>
inline T* sh_coef(T* sh, T* sh_rest, int sh_k, int64_t i, int k) {
    if (!sh_rest) return sh + (i * sh_k + k) * 3;
    return k == 0 ? sh + i * 3 : sh_rest + (i * (sh_k - 1) + k - 1) * 3;
}

}  // namespace

void project_forward(const ProjectInputs& in, const Camera& cam, float* means2d, float* conics, float* depths,
                     int32_t* radii, float* colors) {
    StageTimer timer(kStageProjectForward);
    float campos[3];
    camera_center(cam, campos);
    const int n_bases = (in.sh_degree + 1) * (in.sh_degree + 1);
#pragma omp parallel for schedule(static)
    for (int64_t i = 0; i < in.n; ++i) {
        Proj p;
        bool ok = project_one(in, cam, i, p);
        const float op = in.opacities[i];
        float rx = 0.f, ry = 0.f;
        depths[i] = p.pc[2];
        if (ok) {
            const float iz = 1.f / p.pc[2];
            means2d[2 * i] = cam.fx * p.pc[0] * iz + cam.cx;
            means2d[2 * i + 1] = cam.fy * p.pc[1] * iz + cam.cy;
            const float idet = 1.f / p.det;
            conics[3 * i] = p.c11 * idet;
            conics[3 * i + 1] = -p.c01 * idet;
            conics[3 * i + 2] = p.c00 * idet;
            ok = op >= kAlphaCut;
            if (ok) {
                const float extend = std::min(kMaxExtend, std::sqrt(2.f * std::log(op / kAlphaCut)));
                rx = std::ceil(extend * std::sqrt(p.c00));
                ry = std::ceil(extend * std::sqrt(p.c11));
                const float mx = means2d[2 * i], my = means2d[2 * i + 1];
                ok = mx + rx > 0.f && mx - rx < cam.width && my + ry > 0.f && my - ry < cam.height &&
                     std::isfinite(rx) && std::isfinite(ry);
            }
        } else {
            means2d[2 * i] = means2d[2 * i + 1] = 0.f;
            conics[3 * i] = conics[3 * i + 1] = conics[3 * i + 2] = 0.f;
        }
        radii[2 * i] = ok ? static_cast<int32_t>(rx) : 0;
        radii[2 * i + 1] = ok ? static_cast<int32_t>(ry) : 0;

        if (colors) {
            float* out = colors + 3 * i;
            out[0] = out[1] = out[2] = 0.f;
            if (!ok) continue;
            const float* m = in.means + 3 * i;
            float d[3] = {m[0] - campos[0], m[1] - campos[1], m[2] - campos[2]};
            const float len = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
            const float il = 1.f / std::max(len, 1e-12f);
            float B[16];
            sh_bases(in.sh_degree, d[0] * il, d[1] * il, d[2] * il, B);
            float c[48];
            for (int k = 0; k < n_bases; ++k) {
                const float* ck = sh_coef(in.sh, in.sh_rest, in.sh_k, i, k);
                for (int ch = 0; ch < 3; ++ch) c[3 * k + ch] = ck[ch];
            }
            for (int ch = 0; ch < 3; ++ch) {
                float v = 0.5f;
                for (int k = 0; k < n_bases; ++k) v += B[k] * c[3 * k + ch];
                out[ch] = std::max(v, 0.f);
            }
        }
    }
}

void project_backward(const ProjectInputs& in, const Camera& cam, const int32_t* radii, const float* v_means2d,
                      const float* v_conics, const float* v_depths, const float* v_colors, float* v_means,
                      float* v_quats, float* v_scales, float* v_sh, float* v_sh_rest) {
    StageTimer timer(kStageProjectBackward);
    float campos[3];
    camera_center(cam, campos);
    const int n_bases = (in.sh_degree + 1) * (in.sh_degree + 1);
#pragma omp parallel for schedule(static)
    for (int64_t i = 0; i < in.n; ++i) {
        float* vm = v_means + 3 * i;
        float* vq = v_quats + 4 * i;
        float* vs = v_scales + 3 * i;
        vm[0] = vm[1] = vm[2] = 0.f;
        vq[0] = vq[1] = vq[2] = vq[3] = 0.f;
        vs[0] = vs[1] = vs[2] = 0.f;
        // SH gradients are written once: zeros for culled Gaussians and unused coefficients
        const int sh_from = (radii[2 * i] > 0 && radii[2 * i + 1] > 0 && v_colors) ? n_bases : 0;
        auto zero_sh = [&](int from, int to) {
            for (int k = from; k < to; ++k) {
                float* vk = sh_coef(v_sh, v_sh_rest, in.sh_k, i, k);
                vk[0] = vk[1] = vk[2] = 0.f;
            }
        };
        if (v_sh) zero_sh(sh_from, in.sh_k);
        if (radii[2 * i] <= 0 || radii[2 * i + 1] <= 0) continue;
        Proj p;
        if (!project_one(in, cam, i, p)) {  // cannot happen for a visible Gaussian; keep outputs defined
            if (v_sh) zero_sh(0, sh_from);
            continue;
        }

        const float x = p.pc[0], y = p.pc[1], z = p.pc[2];
        const float iz = 1.f / z, iz2 = iz * iz, iz3 = iz2 * iz;
        const float vx2 = v_means2d[2 * i], vy2 = v_means2d[2 * i + 1];
        float v_pc[3] = {vx2 * cam.fx * iz, vy2 * cam.fy * iz,
                         -vx2 * cam.fx * x * iz2 - vy2 * cam.fy * y * iz2 + (v_depths ? v_depths[i] : 0.f)};

        // conic = inverse of C = [[c00, c01], [c01, c11]]: dL/dC = -A G_A A
        const float idet = 1.f / p.det;
        const float A00 = p.c11 * idet, A01 = -p.c01 * idet, A11 = p.c00 * idet;
        const float G00 = v_conics[3 * i], G01 = 0.5f * v_conics[3 * i + 1], G11 = v_conics[3 * i + 2];
        // H = G_A A
        const float H00 = G00 * A00 + G01 * A01, H01 = G00 * A01 + G01 * A11;
        const float H10 = G01 * A00 + G11 * A01, H11 = G01 * A01 + G11 * A11;
        const float gc00 = -(A00 * H00 + A01 * H10);
        const float gc01 = -(A00 * H01 + A01 * H11);
        const float gc10 = -(A01 * H00 + A11 * H10);
        const float gc11 = -(A01 * H01 + A11 * H11);
        const float Gc[4] = {gc00, 0.5f * (gc01 + gc10), 0.5f * (gc01 + gc10), gc11};  // symmetric

        // cov2d = J covc J^T: G_J = 2 Gc J covc, G_covc = J^T Gc J
        float JS[6];  // J covc
        for (int r = 0; r < 2; ++r)
            for (int c = 0; c < 3; ++c)
                JS[3 * r + c] = p.J[3 * r] * p.covc[c] + p.J[3 * r + 1] * p.covc[3 + c] + p.J[3 * r + 2] * p.covc[6 + c];
        float GJ[6];
        for (int r = 0; r < 2; ++r)
            for (int c = 0; c < 3; ++c) GJ[3 * r + c] = 2.f * (Gc[2 * r] * JS[c] + Gc[2 * r + 1] * JS[3 + c]);
        float Gcovc[9];
        for (int r = 0; r < 3; ++r)
            for (int c = 0; c < 3; ++c)
                Gcovc[3 * r + c] = p.J[r] * (Gc[0] * p.J[c] + Gc[1] * p.J[3 + c]) +
                                   p.J[3 + r] * (Gc[2] * p.J[c] + Gc[3] * p.J[3 + c]);

        // J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]]
        v_pc[2] += GJ[0] * (-cam.fx * iz2) + GJ[2] * (2.f * cam.fx * p.tx * iz3) + GJ[4] * (-cam.fy * iz2) +
                   GJ[5] * (2.f * cam.fy * p.ty * iz3);
        const float v_tx = GJ[2] * (-cam.fx * iz2), v_ty = GJ[5] * (-cam.fy * iz2);
        if (p.clamp_x)
            v_pc[2] += v_tx * p.tx * iz;
        else
            v_pc[0] += v_tx;
        if (p.clamp_y)
            v_pc[2] += v_ty * p.ty * iz;
        else
            v_pc[1] += v_ty;

        // covc = R Σ R^T: G_Σ = R^T G_covc R; Σ = M M^T: G_M = 2 G_Σ M
        float tmp[9], GS[9], GM[9];
        mul33(cam.R, Gcovc, tmp, true, false);
        mul33(tmp, cam.R, GS);
        mul33(GS, p.M, GM);
        for (int k = 0; k < 9; ++k) GM[k] *= 2.f;
        // M = Rq diag(s)
        const float* s = in.scales + 3 * i;
        float GR[9];
        for (int r = 0; r < 3; ++r)
            for (int c = 0; c < 3; ++c) {
                vs[c] += GM[3 * r + c] * p.Rq[3 * r + c];
                GR[3 * r + c] = GM[3 * r + c] * s[c];
            }
        // rotation matrix of the unit quaternion, then the normalisation
        const float w = p.qn[0], qx = p.qn[1], qy = p.qn[2], qz = p.qn[3];
        const float vqn[4] = {
            2.f * (-qz * GR[1] + qy * GR[2] + qz * GR[3] - qx * GR[5] - qy * GR[6] + qx * GR[7]),
            2.f * (qy * GR[1] + qz * GR[2] + qy * GR[3] - 2.f * qx * GR[4] - w * GR[5] + qz * GR[6] + w * GR[7] -
                   2.f * qx * GR[8]),
            2.f * (-2.f * qy * GR[0] + qx * GR[1] + w * GR[2] + qx * GR[3] + qz * GR[5] - w * GR[6] + qz * GR[7] -
                   2.f * qy * GR[8]),
            2.f * (-2.f * qz * GR[0] - w * GR[1] + qx * GR[2] + w * GR[3] - 2.f * qz * GR[4] + qy * GR[5] +
                   qx * GR[6] + qy * GR[7]),
        };
        const float dotq = vqn[0] * w + vqn[1] * qx + vqn[2] * qy + vqn[3] * qz;
        const float iq = 1.f / std::max(p.qnorm, 1e-12f);
        for (int k = 0; k < 4; ++k) vq[k] = (vqn[k] - p.qn[k] * dotq) * iq;

        // means: p_c = R m + t
        for (int c = 0; c < 3; ++c) vm[c] = cam.R[c] * v_pc[0] + cam.R[3 + c] * v_pc[1] + cam.R[6 + c] * v_pc[2];

        if (v_colors && v_sh) {
            const float* m = in.means + 3 * i;
            float d[3] = {m[0] - campos[0], m[1] - campos[1], m[2] - campos[2]};
            const float len = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
            const float il = 1.f / std::max(len, 1e-12f);
            const float u[3] = {d[0] * il, d[1] * il, d[2] * il};
            float B[16];
            sh_bases(in.sh_degree, u[0], u[1], u[2], B);
            float c[48];
            for (int k = 0; k < n_bases; ++k) {
                const float* ck = sh_coef(in.sh, in.sh_rest, in.sh_k, i, k);
                for (int ch = 0; ch < 3; ++ch) c[3 * k + ch] = ck[ch];
            }
            float vrgb[3];
            for (int ch = 0; ch < 3; ++ch) {
                float v = 0.5f;
                for (int k = 0; k < n_bases; ++k) v += B[k] * c[3 * k + ch];
                vrgb[ch] = v >= 0.f ? v_colors[3 * i + ch] : 0.f;  // max(., 0) passes the gradient at >= 0
            }
            float vB[16];
            for (int k = 0; k < n_bases; ++k) {
                vB[k] = 0.f;
                float* vc = sh_coef(v_sh, v_sh_rest, in.sh_k, i, k);
                for (int ch = 0; ch < 3; ++ch) {
                    vc[ch] = B[k] * vrgb[ch];
                    vB[k] += c[3 * k + ch] * vrgb[ch];
                }
            }
            if (in.sh_degree > 0) {
                float vu[3];
                sh_bases_grad(in.sh_degree, u[0], u[1], u[2], vB, vu);
                const float du = vu[0] * u[0] + vu[1] * u[1] + vu[2] * u[2];
                for (int k = 0; k < 3; ++k) vm[k] += (vu[k] - u[k] * du) * il;
            }
        }
    }
}

}  // namespace promptgs
