/* The pinhole camera shared by the eye pass (eye.cl) and the path tracer (pt.cl): one struct,
 * one ray generation.  Host side: clppm/camera.py (CAMERA_DTYPE, Camera.struct). */
#ifndef CLPPM_CAMERA_H
#define CLPPM_CAMERA_H

typedef struct {
    float cpx, cpy, cpz;        /* position (um) */
    float fx, fy, fz;           /* forward, right, up: an orthonormal frame */
    float rx, ry, rz;
    float ux, uy, uz;
    float tan_half, aspect;     /* tan(vertical fov / 2), width / height */
    int width, height;
} Camera;

inline float3 camera_pos(__constant const Camera* c) {
    return (float3)(c->cpx, c->cpy, c->cpz);
}

/* Unit direction of the ray through image point (u, v), in pixels from the top-left corner
 * (clppm/camera.py Camera.ray). */
inline float3 camera_dir(__constant const Camera* c, float u, float v) {
    const float sx = (2.0f * u / (float)c->width - 1.0f) * c->tan_half * c->aspect;
    const float sy = (1.0f - 2.0f * v / (float)c->height) * c->tan_half;
    const float3 fwd = (float3)(c->fx, c->fy, c->fz), right = (float3)(c->rx, c->ry, c->rz);
    const float3 up = (float3)(c->ux, c->uy, c->uz);
    return normalize(fwd + sx * right + sy * up);
}

#endif
