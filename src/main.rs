fn main() {
    println!("isrf");
}
