// seed_structured.cpp: the seed program's structure in C++, the baseline of
// `tessera-bench --suite renderer` (the "seed-structured C++" column).
//
// A line-by-line transcription of `seed_structured.rs` next to it, which is itself a
// transcription of the structure of the seed program (the C++ ray tracer of the seed
// report): the `Vect`, `Ray`, `Camera` and four-channel `Color` classes, objects and
// light sources behind virtual calls (`std::vector<Object*>`, `std::vector<Source*>`), a
// freshly allocated `std::vector<double>` of intersections with every object for every
// ray (camera, reflection and shadow rays), `winningObjectIndex` over that vector, the
// recursive `getColorAt`, the textbook b^2 - 4ac sphere quadratic, a fixed epsilon
// against self-intersection, `double` everywhere and a single thread. The shading is
// that of docs/scene-format.md, sections "The image it gives" (camera, grid
// antialiasing, shading steps 1 to 6, output), without the seed's own bugs, exactly as
// in `seed_structured.rs`.
//
// Scene file: a small recursive-descent JSON reader is built in (no library, no
// header beyond the standard ones). It reads the scene schema of docs/scene-format.md
// as far as the seed scene uses it and the optional keys around it: `lights`,
// `objects` (`sphere`, `plan`/`plane`), `camera`, `image`, `ambient`; vectors and
// colours as strings of numbers or arrays. It does no validation: it is meant for
// `scenes/seed.json`, which is fixed, not for arbitrary input.
//
// Build:  g++ -O3 -march=x86-64-v2 render/benches/seed_structured.cpp -o seed_structured
// Usage:  seed_structured SCENE.json [-o OUT.ppm] [--width W] [--height H] [--aa N]
//                                    [--max-depth D]
// Prints one line on stderr: size, parse and render times, and writes the image as a
// binary PPM if -o is given.
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <map>
#include <memory>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

// ---------------------------------------------------------------------------------------
// A tiny JSON reader: values are null, booleans, numbers, strings, arrays and objects.
struct Json {
  enum Kind { NUL, BOOL, NUM, STR, ARR, OBJ } kind = NUL;
  double num = 0;
  std::string str;
  std::vector<Json> arr;
  std::map<std::string, Json> obj;

  const Json* get(const std::string& key) const {
    auto it = obj.find(key);
    return it == obj.end() ? nullptr : &it->second;
  }
};

struct JsonReader {
  const char* p;
  const char* end;

  [[noreturn]] void fail(const char* what) {
    throw std::runtime_error(std::string("bad JSON: ") + what);
  }
  void skip() {
    while (p < end && (*p == ' ' || *p == '\n' || *p == '\r' || *p == '\t')) p++;
  }
  bool eat(char c) {
    skip();
    if (p < end && *p == c) {
      p++;
      return true;
    }
    return false;
  }
  void expect(char c) {
    if (!eat(c)) fail("unexpected character");
  }
  std::string string() {
    expect('"');
    std::string s;
    while (p < end && *p != '"') {
      if (*p == '\\') {
        p++;
        if (p >= end) fail("unterminated escape");
        char c = *p;
        s += c == 'n' ? '\n' : c == 't' ? '\t' : c;  // enough for scene files
      } else {
        s += *p;
      }
      p++;
    }
    if (p >= end) fail("unterminated string");
    p++;
    return s;
  }
  Json value() {
    skip();
    if (p >= end) fail("unexpected end");
    Json v;
    if (*p == '{') {
      p++;
      v.kind = Json::OBJ;
      if (eat('}')) return v;
      do {
        std::string key = string();
        expect(':');
        v.obj[key] = value();
      } while (eat(','));
      expect('}');
    } else if (*p == '[') {
      p++;
      v.kind = Json::ARR;
      if (eat(']')) return v;
      do v.arr.push_back(value());
      while (eat(','));
      expect(']');
    } else if (*p == '"') {
      v.kind = Json::STR;
      v.str = string();
    } else if (!strncmp(p, "true", 4) || !strncmp(p, "false", 5)) {
      v.kind = Json::BOOL;
      v.num = *p == 't';
      p += *p == 't' ? 4 : 5;
    } else if (!strncmp(p, "null", 4)) {
      p += 4;
    } else {
      char* after;
      v.kind = Json::NUM;
      v.num = strtod(p, &after);
      if (after == p) fail("expected a value");
      p = after;
    }
    return v;
  }
};

// The numbers of a VEC or COLOR: "x y z" or [x, y, z].
static std::vector<double> numbers(const Json& v) {
  std::vector<double> out;
  if (v.kind == Json::ARR) {
    for (auto& x : v.arr) out.push_back(x.num);
  } else {
    std::istringstream in(v.str);
    double x;
    while (in >> x) out.push_back(x);
  }
  return out;
}

// ---------------------------------------------------------------------------------------
// The seed's classes.

// Hits at t <= ACCURACY are taken to be the surface the ray leaves, as in the seed.
static const double ACCURACY = 1e-6;
// The seed's `special` value that selects the checkerboard.
static const double CHECKER = 2.0;

struct Vect {
  double x = 0, y = 0, z = 0;
  Vect() {}
  Vect(double x, double y, double z) : x(x), y(y), z(z) {}
  double magnitude() const { return std::sqrt(dot(*this)); }
  Vect normalize() const { return *this / magnitude(); }
  double dot(Vect o) const { return x * o.x + y * o.y + z * o.z; }
  Vect cross(Vect o) const {
    return Vect(y * o.z - z * o.y, z * o.x - x * o.z, x * o.y - y * o.x);
  }
  Vect operator+(Vect o) const { return Vect(x + o.x, y + o.y, z + o.z); }
  Vect operator-(Vect o) const { return Vect(x - o.x, y - o.y, z - o.z); }
  Vect operator*(double s) const { return Vect(x * s, y * s, z * s); }
  Vect operator/(double s) const { return Vect(x / s, y / s, z / s); }
  Vect operator-() const { return Vect(-x, -y, -z); }
};

static Vect vect(const Json& v) {
  std::vector<double> n = numbers(v);
  return Vect(n.at(0), n.at(1), n.at(2));
}

// A half-line origin + t * direction, |direction| = 1.
struct Ray {
  Vect origin, direction;
};

// r g b plus the `special` channel that selects the material (0 matte, (0, 1]
// reflective, 2 checkerboard).
struct Color {
  double red = 0, green = 0, blue = 0, special = 0;
  Color() {}
  Color(double r, double g, double b, double s) : red(r), green(g), blue(b), special(s) {}

  // Component-wise product (the seed's colorMultiply), keeping this colour's special.
  Color multiply(Color o) const {
    return Color(red * o.red, green * o.green, blue * o.blue, special);
  }
  // Channel-wise sum, keeping this colour's special (colorAdd).
  Color operator+(Color o) const {
    return Color(red + o.red, green + o.green, blue + o.blue, special);
  }
  // Scales r g b, keeping the special (colorScalar).
  Color operator*(double s) const { return Color(red * s, green * s, blue * s, special); }

  // Shading step 6: light above white spills into every channel in proportion, then
  // each channel is clamped to [0, 1].
  Color clip() const {
    double all_light = red + green + blue;
    double excess_light = all_light - 3.0;
    Color c = *this;
    if (excess_light > 0.0) {
      c.red += excess_light * (c.red / all_light);
      c.green += excess_light * (c.green / all_light);
      c.blue += excess_light * (c.blue / all_light);
    }
    auto clamp = [](double v) { return v < 0.0 ? 0.0 : v > 1.0 ? 1.0 : v; };
    return Color(clamp(c.red), clamp(c.green), clamp(c.blue), c.special);
  }
};

// The pinhole camera.
struct Camera {
  Vect position, forward, right, up;
  Camera(Vect position, Vect look_at) : position(position) {
    forward = (look_at - position).normalize();
    right = Vect(0.0, 1.0, 0.0).cross(forward).normalize();
    up = forward.cross(right);
  }
  // The ray through the image-plane point (x, y), in units of the shorter image side
  // from the image centre.
  Ray ray(double x, double y) const {
    return Ray{position, (forward + right * x + up * y).normalize()};
  }
};

// The seed's abstract Object: every scene object is reached through virtual calls.
class Object {
 public:
  virtual ~Object() {}
  virtual Color getColor() const = 0;
  // The outward unit normal at a point of the surface.
  virtual Vect getNormalAt(Vect p) const = 0;
  // The nearest t > ACCURACY where the ray meets the object, or -1 if there is none.
  virtual double findIntersection(const Ray& ray) const = 0;
};

// The seed's abstract light Source.
class Source {
 public:
  virtual ~Source() {}
  virtual Vect getLightPosition() const = 0;
  virtual Color getLightColor() const = 0;
};

class Sphere : public Object {
  Vect center;
  double radius;
  Color color;

 public:
  Sphere(Vect c, double r, Color col) : center(c), radius(r), color(col) {}
  Color getColor() const override { return color; }
  Vect getNormalAt(Vect p) const override { return (p - center).normalize(); }
  // The textbook quadratic a t^2 + b t + c = 0, a = 1 for unit directions.
  double findIntersection(const Ray& ray) const override {
    Vect oc = ray.origin - center;
    double b = 2.0 * ray.direction.dot(oc);
    double c = oc.dot(oc) - radius * radius;
    double discriminant = b * b - 4.0 * c;
    if (discriminant <= 0.0) return -1.0;
    double root = std::sqrt(discriminant);
    double root_1 = (-b - root) / 2.0;
    if (root_1 > ACCURACY) return root_1;
    double root_2 = (-b + root) / 2.0;
    return root_2 > ACCURACY ? root_2 : -1.0;
  }
};

class Plane : public Object {
  Vect normal;  // unit
  double distance;
  Color color;

 public:
  Plane(Vect n, double d, Color col) : normal(n), distance(d), color(col) {}
  Color getColor() const override { return color; }
  Vect getNormalAt(Vect) const override { return normal; }
  double findIntersection(const Ray& ray) const override {
    double a = ray.direction.dot(normal);
    if (a == 0.0) return -1.0;  // parallel to the plane
    double b = normal.dot(ray.origin - normal * distance);
    double t = -b / a;
    return t > ACCURACY ? t : -1.0;
  }
};

class Light : public Source {
  Vect position;
  Color color;

 public:
  Light(Vect p, Color c) : position(p), color(c) {}
  Vect getLightPosition() const override { return position; }
  Color getLightColor() const override { return color; }
};

// The distance to every object along the ray, in object order (-1 where it misses), in
// a vector allocated for this ray.
static std::vector<double> intersections(const std::vector<Object*>& objects, const Ray& ray) {
  std::vector<double> out;
  for (Object* o : objects) out.push_back(o->findIntersection(ray));
  return out;
}

// The index of the nearest hit (the smallest positive distance, the lowest index on a
// tie), or -1 if the ray hits nothing.
static int winningObjectIndex(const std::vector<double>& intersections) {
  int winner = -1;
  for (size_t index = 0; index < intersections.size(); index++) {
    double t = intersections[index];
    if (t > 0.0 && (winner < 0 || t < intersections[winner])) winner = (int)index;
  }
  return winner;
}

struct SeedScene {
  std::vector<Object*> objects;
  std::vector<Source*> lights;
  Camera camera{Vect(3, 1.5, -4), Vect(0, 0, 0)};
  double ambient = 0.2;
  int width = 600, height = 400, aadepth = 1, max_depth = 10;

  ~SeedScene() {
    for (Object* o : objects) delete o;
    for (Source* l : lights) delete l;
  }

  // The clipped colour seen along a camera ray.
  Color trace(const Ray& ray) const {
    std::vector<double> hits = intersections(objects, ray);
    int index = winningObjectIndex(hits);
    if (index < 0) return Color();
    Vect position = ray.origin + ray.direction * hits[index];
    return getColorAt(position, ray.direction, index, 0);
  }

  // The clipped colour at `position` on object `index`, reached along `direction` at
  // reflection depth `depth`.
  Color getColorAt(Vect position, Vect direction, int index, int depth) const {
    const Object* object = objects[index];
    Color object_color = object->getColor();
    double special = object_color.special;
    if (special == CHECKER) {
      long long square = (long long)std::floor(position.x) + (long long)std::floor(position.z);
      double v = ((square % 2) + 2) % 2 == 1 ? 1.0 : 0.0;
      object_color = Color(v, v, v, special);
    }
    Vect normal = object->getNormalAt(position);
    if (normal.dot(direction) > 0.0) normal = -normal;
    Color final_color = object_color * ambient;

    bool reflective = special > 0.0 && special <= 1.0;
    Vect reflection_direction;
    if (reflective)
      reflection_direction = (direction - normal * (2.0 * direction.dot(normal))).normalize();
    if (reflective && depth < max_depth) {
      Ray reflection_ray{position, reflection_direction};
      std::vector<double> reflection_intersections = intersections(objects, reflection_ray);
      int hit = winningObjectIndex(reflection_intersections);
      if (hit >= 0) {
        Vect hit_position = position + reflection_direction * reflection_intersections[hit];
        Color reflection_color = getColorAt(hit_position, reflection_direction, hit, depth + 1);
        final_color = final_color + reflection_color * special;
      }
    }

    for (const Source* light : lights) {
      Vect to_light = light->getLightPosition() - position;
      double distance_to_light = to_light.magnitude();
      Vect light_direction = to_light / distance_to_light;
      double cosine_angle = normal.dot(light_direction);
      if (cosine_angle <= 0.0) continue;
      Ray shadow_ray{position, light_direction};
      std::vector<double> shadow_hits = intersections(objects, shadow_ray);
      bool shadowed = false;
      for (double t : shadow_hits)
        if (t > 0.0 && t <= distance_to_light) {
          shadowed = true;
          break;
        }
      if (shadowed) continue;
      Color light_color = light->getLightColor();
      final_color = final_color + object_color.multiply(light_color) * cosine_angle;
      if (reflective) {
        double specular = reflection_direction.dot(light_direction);
        if (specular > 0.0) {
          double s2 = specular * specular, s4 = s2 * s2, s8 = s4 * s4;
          final_color = final_color + light_color * (s8 * s2 * special);
        }
      }
    }
    return final_color.clip();
  }

  // RGB8, rows top to bottom.
  std::vector<unsigned char> render() const {
    double w = width, h = height;
    double short_side = w < h ? w : h;
    double n = aadepth;
    std::vector<unsigned char> rgb;
    rgb.reserve((size_t)width * height * 3);
    auto to_byte = [](double v) {
      v = v < 0.0 ? 0.0 : v > 1.0 ? 1.0 : v;
      return (unsigned char)std::round(v * 255.0);
    };
    for (int j = 0; j < height; j++) {
      for (int i = 0; i < width; i++) {
        Color sum;
        for (int b = 0; b < aadepth; b++) {
          double y = (h / 2.0 - (j + (b + 0.5) / n)) / short_side;
          for (int a = 0; a < aadepth; a++) {
            double x = (i + (a + 0.5) / n - w / 2.0) / short_side;
            sum = sum + trace(camera.ray(x, y));
          }
        }
        Color mean = sum * (1.0 / (n * n));
        rgb.push_back(to_byte(mean.red));
        rgb.push_back(to_byte(mean.green));
        rgb.push_back(to_byte(mean.blue));
      }
    }
    return rgb;
  }
};

static void load(SeedScene& s, const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw std::runtime_error("cannot read " + path);
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  JsonReader reader{text.data(), text.data() + text.size()};
  Json root = reader.value();
  if (const Json* camera = root.get("camera")) {
    Vect position(3, 1.5, -4), look_at(0, 0, 0);
    if (const Json* p = camera->get("position")) position = vect(*p);
    if (const Json* l = camera->get("look_at")) look_at = vect(*l);
    s.camera = Camera(position, look_at);
  }
  if (const Json* image = root.get("image")) {
    if (const Json* v = image->get("width")) s.width = (int)v->num;
    if (const Json* v = image->get("height")) s.height = (int)v->num;
    if (const Json* v = image->get("aa")) s.aadepth = (int)v->num;
    if (const Json* v = image->get("max_depth")) s.max_depth = (int)v->num;
  }
  if (const Json* a = root.get("ambient")) s.ambient = a->num;
  if (const Json* lights = root.get("lights")) {
    for (const Json& l : lights->arr) {
      std::vector<double> c = numbers(*l.get("color"));
      s.lights.push_back(new Light(vect(*l.get("position")), Color(c.at(0), c.at(1), c.at(2), 0)));
    }
  }
  if (const Json* objects = root.get("objects")) {
    for (const Json& o : objects->arr) {
      std::vector<double> c = numbers(*o.get("color"));
      Color color(c.at(0), c.at(1), c.at(2), c.at(3));
      if (o.get("type")->str == "sphere")
        s.objects.push_back(new Sphere(vect(*o.get("center")), o.get("radius")->num, color));
      else
        s.objects.push_back(new Plane(vect(*o.get("normal")).normalize(), o.get("distance")->num, color));
    }
  }
}

int main(int argc, char** argv) {
  using clock = std::chrono::steady_clock;
  auto t0 = clock::now();
  std::string scene_path, out;
  int width = 0, height = 0, aa = 0, max_depth = -1;
  for (int i = 1; i < argc; i++) {
    std::string a = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) {
        fprintf(stderr, "missing value for %s\n", a.c_str());
        exit(2);
      }
      return argv[++i];
    };
    if (a == "-o") out = next();
    else if (a == "--width") width = std::stoi(next());
    else if (a == "--height") height = std::stoi(next());
    else if (a == "--aa") aa = std::stoi(next());
    else if (a == "--max-depth") max_depth = std::stoi(next());
    else if (a[0] == '-') {
      fprintf(stderr, "unknown option %s\n", a.c_str());
      return 2;
    } else scene_path = a;
  }
  if (scene_path.empty()) {
    fprintf(stderr,
            "usage: %s SCENE.json [-o OUT.ppm] [--width W] [--height H] [--aa N] [--max-depth D]\n",
            argv[0]);
    return 2;
  }
  SeedScene scene;
  try {
    load(scene, scene_path);
  } catch (std::exception& e) {
    fprintf(stderr, "%s: %s\n", scene_path.c_str(), e.what());
    return 1;
  }
  if (width) scene.width = width;
  if (height) scene.height = height;
  if (aa) scene.aadepth = aa;
  if (max_depth >= 0) scene.max_depth = max_depth;
  auto t1 = clock::now();
  std::vector<unsigned char> rgb = scene.render();
  auto t2 = clock::now();
  if (!out.empty()) {
    FILE* f = fopen(out.c_str(), "wb");
    if (!f) {
      fprintf(stderr, "cannot write %s\n", out.c_str());
      return 1;
    }
    fprintf(f, "P6\n%d %d\n255\n", scene.width, scene.height);
    fwrite(rgb.data(), 1, rgb.size(), f);
    fclose(f);
  }
  auto s = [](clock::time_point a, clock::time_point b) {
    return std::chrono::duration<double>(b - a).count();
  };
  fprintf(stderr, "%s: %dx%d, aa %d, 1 thread: parse %.3f s, render %.3f s\n",
          out.empty() ? "(no image)" : out.c_str(), scene.width, scene.height, scene.aadepth,
          s(t0, t1), s(t1, t2));
  return 0;
}
